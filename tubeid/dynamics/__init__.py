"""tubeid.dynamics"""
