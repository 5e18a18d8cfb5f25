"""egcbf: Deep Equivariant Multi-Agent Control Barrier Functions for quadrotor swarms (built on groupcanon)."""

from ._version import __version__

__all__ = ["__version__"]
