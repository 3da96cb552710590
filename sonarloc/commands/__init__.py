"""sonarloc.commands"""
