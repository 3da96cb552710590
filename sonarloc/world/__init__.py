"""sonarloc.world"""
