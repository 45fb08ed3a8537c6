"""tubeid.measured"""
