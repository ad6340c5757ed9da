"""The package version (the bottom floor: every module may read it)."""

__version__ = "0.1.0"
