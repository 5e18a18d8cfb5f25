"""The version of both distributions built from this repository, ``groupcanon`` and ``egcbf`` (which ships
groupcanon too): their one version source, read by ``pyproject.toml`` and ``packaging/groupcanon/pyproject.toml``."""

__version__ = "0.1.0"
