"""Networks: the graph transformer layer, and the CBF and policy networks (equivariance from groupcanon)."""

from .layers import GraphTransformerLayer, mlp
from .models import (
    GROUPS,
    CBFNet,
    GraphEncoder,
    ModelConfig,
    PolicyNet,
    edge_type,
    frames_for,
    make_group,
    node_type,
)

__all__ = [
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
]
