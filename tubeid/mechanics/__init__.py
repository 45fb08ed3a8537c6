"""tubeid.mechanics"""
