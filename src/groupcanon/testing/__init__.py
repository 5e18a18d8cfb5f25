"""Testing kit: property-test groups, feature types and equivariant functions (yours or ours).

from groupcanon.testing import check_group_axioms, check_action_laws, assert_equivariant, strategies
"""

from . import strategies
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
