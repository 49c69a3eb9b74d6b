"""starlog's version (read by the build, recorded in every provenance record)."""

__version__ = "0.1.0"
