"""tubeid.uncertainty"""
