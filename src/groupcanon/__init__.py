"""groupcanon: equivariance for any graph-neural-network layer by canonicalization.

    f_v = rho_out(g_v) [ M( rho_in(g_v^-1) F ) ]_v

Public surface: :class:`Group`, :class:`FeatureType`, :class:`FieldType`, :class:`Canonicalize`, and the
submodules :mod:`groups`, :mod:`features`, :mod:`frames` and :mod:`testing`.
"""

from . import features, frames, groups
from ._version import __version__ as __version__
from .canonicalize import Canonicalize, CanonicalizedLayer, globalize, localize
from .features import FeatureType
from .field_type import FieldType
from .group import Group

__all__ = [
    "Canonicalize",
    "CanonicalizedLayer",
    "FeatureType",
    "FieldType",
    "Group",
    "features",
    "frames",
    "globalize",
    "groups",
    "localize",
    "testing",
]


def __getattr__(name):  # import the testing kit only when asked for
    if name == "testing":
        import importlib

        return importlib.import_module(".testing", __name__)
    raise AttributeError(f"module 'groupcanon' has no attribute {name!r}")
