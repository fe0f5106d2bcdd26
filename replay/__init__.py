"""MCAP recording and replay (a later issue)."""
