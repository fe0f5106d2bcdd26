"""Shared test configuration."""

import os

# keep hypothesis' example database out of the work tree
os.environ.setdefault("HYPOTHESIS_STORAGE_DIRECTORY", "/tmp/stockpile-hypothesis")
