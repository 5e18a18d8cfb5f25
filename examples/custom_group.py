"""A new group (C*: planar rotation-scalings) and feature type, property-tested, wrapping a PyG layer."""

import torch
from hypothesis import given, settings
from torch_geometric.nn import TransformerConv

from groupcanon import Canonicalize, FeatureType, FieldType, Group
from groupcanon.features import Scalar
from groupcanon.testing import assert_equivariant, check_action_laws, check_group_axioms
from groupcanon.testing import strategies as gst


def cmul(a, b):  # (a0 + i a1)(b0 + i b1); batch dimensions broadcast
    (a0, a1), (b0, b1) = a.unbind(-1), b.unbind(-1)
    return torch.stack((a0 * b0 - a1 * b1, a0 * b1 + a1 * b0), -1)


class CStar(Group):
    """Nonzero complex numbers under multiplication: rotation by arg z, scaling by |z|. Layout (*batch, 2) = (a, b)."""

    element_shape = (2,)

    def identity(self, *batch, dtype=None, device=None):
        return torch.tensor([1.0, 0.0], dtype=dtype, device=device).expand(*batch, 2).clone()

    def compose(self, a, b):
        return cmul(a, b)

    def inverse(self, a):
        return torch.stack((a[..., 0], -a[..., 1]), -1) / (a * a).sum(-1, keepdim=True)

    def sample(self, *batch, generator=None, dtype=None, device=None):  # Haar angle, log-normal modulus
        theta = 2 * torch.pi * torch.rand(*batch, generator=generator, dtype=dtype, device=device)
        log_r = torch.randn(*batch, generator=generator, dtype=theta.dtype, device=device)
        return torch.stack((theta.cos(), theta.sin()), -1) * log_r.exp().unsqueeze(-1)

    def special_elements(self, dtype=None, device=None):  # half turn, near-full turn, tiny and huge moduli
        z = [[1.0, 0], [-1, 1e-11], [1 - 1e-11, -1e-11], [1e-3, 0], [0, 1e3]]
        return torch.tensor(z, dtype=dtype, device=device)


class Spin(FeatureType):
    """A planar vector rotated by arg z and scaled by |z|^w (w = 1: multiplication by z; w = 0: rotation only)."""

    dim = 2

    def __init__(self, w=1.0):
        self.w = w

    def act(self, g, x):
        return cmul(g, x) * (g * g).sum(-1, keepdim=True) ** ((self.w - 1) / 2)

    def __repr__(self):
        return f"Spin({self.w:g})"


G = CStar()
t_in, t_out = FieldType(G, [Scalar(4), Spin(1), Spin(0)]), FieldType(G, [Scalar(3), Spin(1), Spin(2)])
torch.manual_seed(0)
layer = Canonicalize(G, t_in, t_out)(TransformerConv(t_in.dim, t_out.dim)).double()


def model(x, edge_index):  # frame of node v = its own Spin(1) vector, which transforms as z . v: g_v -> z g_v
    return layer(x, edge_index, frames=t_in.get(x, 1))


@settings(max_examples=25, deadline=None, database=None)
@given(graph=gst.graphs(max_nodes=16), seed=gst.seeds())
def check_random_graphs(graph, seed):
    x = torch.randn(graph.num_nodes, t_in.dim, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    assert_equivariant(model, G, (x, graph.edge_index), in_types={0: t_in}, out_types=t_out, rtol=1e-10)


if __name__ == "__main__":
    print(f"group axioms of {G}: max error {check_group_axioms(G):.1e}")
    for ft in (Spin(1), Spin(0), Spin(2.5), t_in, t_out):
        print(f"action laws of {ft!r}: max error {check_action_laws(G, ft):.1e}")
    check_random_graphs()
    print("Canonicalize(TransformerConv) is C*-equivariant on 25 random graphs (hypothesis): OK")
