"""egcbf: Deep Equivariant Multi-Agent Control Barrier Functions for quadrotor swarms (built on groupcanon)."""

__version__ = "0.1.0"
