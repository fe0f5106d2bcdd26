"""What every command and service shares, below every other package: the command line's
vocabulary (shared options, durations with units), progress output and logging setup.

It imports nothing of the project, so any layer may use it.
"""
