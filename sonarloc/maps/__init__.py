"""sonarloc.maps"""
