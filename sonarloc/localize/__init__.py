"""sonarloc.localize"""
