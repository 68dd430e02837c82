"""Session manager, recorder, launcher and CLI of the bike testbed"""
