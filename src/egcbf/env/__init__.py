"""The swarm environment: config, batched state, reset/step, safety masks, obstacles, LiDAR, sampling."""

from .config import EnvConfig
from .lidar import LidarScan, lidar_scan, ray_directions
from .obstacles import Obstacles, sample_obstacles
from .sampling import sample_separated_points
from .swarm import NonFiniteStateError, StepInfo, SwarmEnv, SwarmState, cast_lidar, safety_masks

__all__ = [
    "EnvConfig",
    "LidarScan",
    "NonFiniteStateError",
    "Obstacles",
    "StepInfo",
    "SwarmEnv",
    "SwarmState",
    "cast_lidar",
    "lidar_scan",
    "ray_directions",
    "safety_masks",
    "sample_obstacles",
    "sample_separated_points",
]
