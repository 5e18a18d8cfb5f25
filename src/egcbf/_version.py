"""The version of the distribution (egcbf and groupcanon ship together); pyproject.toml reads it."""

__version__ = "0.1.0"
