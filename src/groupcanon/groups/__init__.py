"""Built-in groups. Every group documents its element layout in its docstring."""

from .cyclic import Cyclic
from .o2 import O2
from .product import Product
from .se2 import SE2, CyclicSE2, CyclicSE2xR, SE2xR
from .so2 import SO2
from .so3 import SE3, SO3
from .translation import Translation
from .trivial import Trivial

__all__ = [
    "O2",
    "SE2",
    "SE3",
    "SO2",
    "SO3",
    "Cyclic",
    "CyclicSE2",
    "CyclicSE2xR",
    "Product",
    "SE2xR",
    "Translation",
    "Trivial",
]
