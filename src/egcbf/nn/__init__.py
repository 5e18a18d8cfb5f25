"""Networks: the graph transformer layer, and the CBF and policy networks (equivariance from groupcanon)."""

from .layers import GraphTransformerLayer, mlp
from .models import (
    BASE_LAWS,
    GROUPS,
    CBFNet,
    GraphEncoder,
    ModelConfig,
    PolicyNet,
    edge_type,
    frames_for,
    make_group,
    node_type,
    sensing,
)

__all__ = [
    "BASE_LAWS",
    "GROUPS",
    "CBFNet",
    "GraphEncoder",
    "GraphTransformerLayer",
    "ModelConfig",
    "PolicyNet",
    "edge_type",
    "frames_for",
    "make_group",
    "mlp",
    "node_type",
    "sensing",
]
