"""tubeid.identification"""
