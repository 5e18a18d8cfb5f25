"""Controllers: the equivariant nominal (geometric) controller; CBF-QP baselines live beside it."""

from .nominal import (
    DEFAULT_GAINS,
    DEFAULT_MAX_POSITION_ERROR,
    GOAL_TYPE,
    NominalGains,
    desired_heading,
    nominal_acceleration,
    nominal_control,
    track_acceleration,
)

__all__ = [
    "DEFAULT_GAINS",
    "DEFAULT_MAX_POSITION_ERROR",
    "GOAL_TYPE",
    "NominalGains",
    "desired_heading",
    "nominal_acceleration",
    "nominal_control",
    "track_acceleration",
]
