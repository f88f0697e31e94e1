"""The package version, below every layer (stamped into references and sweeps)."""

__version__ = "0.1.0"
