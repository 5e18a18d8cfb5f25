"""Testing kit: property-test groups, feature types and equivariant functions (yours or ours).

from groupcanon.testing import check_group_axioms, check_action_laws, assert_equivariant, strategies

The checks need only torch; :mod:`~groupcanon.testing.strategies` (imported on first use) needs hypothesis, the
``testing`` extra: ``pip install "groupcanon[testing]"``.
"""

from .checks import (
    assert_equivariant,
    assert_invariant,
    check_action_laws,
    check_group_axioms,
    default_atol,
    equivariance_error,
)

__all__ = [
    "assert_equivariant",
    "assert_invariant",
    "check_action_laws",
    "check_group_axioms",
    "default_atol",
    "equivariance_error",
    "strategies",
]


def __getattr__(name):  # hypothesis is imported only when the strategies are asked for
    if name == "strategies":
        import importlib

        try:
            return importlib.import_module(".strategies", __name__)
        except ModuleNotFoundError as err:
            if err.name != "hypothesis":
                raise
            raise ModuleNotFoundError(
                "groupcanon.testing.strategies needs hypothesis, an optional extra: pip install 'groupcanon[testing]' "
                "(or pip install 'hypothesis>=6.100')",
                name="hypothesis",
            ) from err
    raise AttributeError(f"module 'groupcanon.testing' has no attribute {name!r}")
