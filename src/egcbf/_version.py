"""egcbf's version: groupcanon's (one number for both distributions of the repository: src/groupcanon/_version.py)."""

from groupcanon._version import __version__

__all__ = ["__version__"]
