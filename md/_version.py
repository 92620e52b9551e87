"""The package version (layer 0), read by the trajectory writer and ``md --version``."""

__version__ = "0.1.0"
