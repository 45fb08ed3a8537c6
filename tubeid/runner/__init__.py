"""tubeid.runner"""
