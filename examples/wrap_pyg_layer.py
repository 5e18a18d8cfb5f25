"""Tutorial: make unmodified torch_geometric layers equivariant to SE(2) x R with ``Canonicalize``.

The scene is a swarm of drones in 3-D. Gravity points down, so the symmetry is ``groups.SE2xR()``: rotations about
the world z axis and all 3-D translations. Each drone carries

    scalars (2)  e.g. mass and battery        invariant
    heading (3)  its body x axis               rotated
    velocity (3)                               rotated
    position (3)                               rotated and translated

and every drone gets a frame ``g_v`` (its yaw and its position) from :func:`groupcanon.frames.se2xr_frame`. The wrapped
layers see each neighbourhood in the receiver's frame, so the network is equivariant although the layers inside are
plain ``TransformerConv`` / ``GATv2Conv`` / MLP. The same code with ``groups.Trivial()`` is the ordinary,
non-equivariant network.

    python examples/wrap_pyg_layer.py [--device cpu] [--nodes 300]
"""

from __future__ import annotations

import argparse
import sys

import torch
from torch import nn
from torch_geometric.nn import GATv2Conv, TransformerConv

from groupcanon import Canonicalize, FieldType, groups
from groupcanon.features import Point, Scalar, Vector
from groupcanon.frames import se2xr_frame
from groupcanon.testing import assert_equivariant, equivariance_error


def radius_graph(pos: torch.Tensor, r: float) -> torch.Tensor:
    """Edges ``u -> v`` between drones closer than ``r`` (no self loops), shape ``(2, E)``.

    ``torch_geometric.nn.radius_graph`` does the same in O(N) memory but needs torch-cluster or pyg-lib; for a small
    demo the dense O(N^2) distance matrix is fine.
    """
    try:
        from torch_geometric.nn import radius_graph as pyg_radius_graph

        return pyg_radius_graph(pos, r=r, max_num_neighbors=pos.shape[0])
    except ImportError:
        close = torch.cdist(pos, pos) < r
        close.fill_diagonal_(False)
        dst, src = close.nonzero(as_tuple=True)
        return torch.stack((src, dst))


class SwarmNet(nn.Module):
    """TransformerConv -> node-wise MLP -> GATv2Conv, each wrapped by ``Canonicalize(G, ...)``.

    Output per drone: 4 invariant scalars and one vector (e.g. a desired acceleration), in the world frame.
    """

    def __init__(self, G: groups.Group):
        super().__init__()
        self.G = G
        # 1. Declare how every channel transforms. A dict names the fields, so they can be read back by name.
        self.in_type = FieldType(
            G, {"scalars": Scalar(2), "heading": Vector(3), "velocity": Vector(3), "position": Point(3)}
        )
        self.hidden_type = FieldType(G, [Scalar(24), Vector(3, n=4)])
        self.out_type = FieldType(G, [Scalar(4), Vector(3)])
        t_in, t_hid, t_out = self.in_type, self.hidden_type, self.out_type

        # 2. Wrap unmodified layers. TransformerConv takes a (source, target) pair: "pair" mode is detected.
        self.conv1 = Canonicalize(G, t_in, t_hid)(TransformerConv(t_in.dim, t_hid.dim, heads=2, concat=False))
        # A node-wise MLP has no edges: mode="node" applies it to each drone's features in the drone's own frame.
        mlp = nn.Sequential(nn.Linear(t_hid.dim, 64), nn.SiLU(), nn.Linear(64, t_hid.dim))
        self.mlp = Canonicalize(G, t_hid, t_hid, mode="node")(mlp)
        # GATv2Conv would add self loops by node index, which is wrong on the expanded graph that Canonicalize
        # builds: switch them off in the layer and let the wrapper add them (in the right frame).
        gat = GATv2Conv(t_hid.dim, t_out.dim, heads=2, concat=False, add_self_loops=False)
        self.conv2 = Canonicalize(G, t_hid, t_out, self_loops=True)(gat)

    def frames(self, x: torch.Tensor) -> torch.Tensor:
        """One group element per drone, ``(N, *G.element_shape)``: yaw from the heading, origin at the position."""
        if isinstance(self.G, groups.Trivial):
            return self.G.identity(x.shape[0], dtype=x.dtype, device=x.device)  # (N, 0): nothing to undo
        return se2xr_frame(self.in_type.get(x, "heading"), self.in_type.get(x, "position"))

    def forward(self, x: torch.Tensor, edge_index: torch.Tensor) -> torch.Tensor:
        frames = self.frames(x)
        h = self.conv1(x, edge_index, frames=frames)
        h = h + self.mlp(h, frames=frames)  # residual: the sum of two equivariant maps is equivariant
        return self.conv2(h, edge_index, frames=frames)


def make_scene(n: int, box: float, generator: torch.Generator) -> torch.Tensor:
    """Random drones: ``(n, 11)`` = scalars (2), heading (3, horizontal unit vector), velocity (3), position (3)."""
    yaw = 2 * torch.pi * torch.rand(n, generator=generator)
    heading = torch.stack((yaw.cos(), yaw.sin(), torch.zeros(n)), dim=-1)
    velocity = torch.randn(n, 3, generator=generator)
    position = box * torch.rand(n, 3, generator=generator)
    scalars = torch.rand(n, 2, generator=generator)
    return torch.cat((scalars, heading, velocity, position), dim=-1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda (default: cpu)")
    parser.add_argument("--nodes", type=int, default=300, help="number of drones (default: 300)")
    parser.add_argument("--radius", type=float, default=4.0, help="communication radius in metres (default: 4)")
    args = parser.parse_args()
    device = torch.device(args.device)

    G = groups.SE2xR()
    torch.manual_seed(0)
    model = SwarmNet(G).to(device)

    box = 20.0
    x = make_scene(args.nodes, box, torch.Generator().manual_seed(0)).to(device)
    # distances are invariant under rotations and translations, so the graph is too
    edge_index = radius_graph(model.in_type.get(x, "position"), args.radius)
    n, e = x.shape[0], edge_index.shape[1]
    print(
        f"scene: {n} drones in a {box:g} m box, radius graph r = {args.radius:g} m: {e} edges "
        f"(mean in-degree {e / n:.1f}), device {device}"
    )

    y = model(x, edge_index)
    print(f"model: {model.in_type.dim} -> {model.out_type.dim} channels per drone, output {model.out_type}")

    # 3. Check: rotate about z and translate the whole scene; outputs must rotate (and scalars stay put).
    g = G.sample(8, generator=torch.Generator().manual_seed(1), dtype=torch.float64).to(device)
    check = {"in_types": {0: model.in_type}, "out_types": model.out_type, "g": g.float()}
    print("max |f(g.x) - g.f(x)| over 8 random rotations about z + 3-D translations (|t| ~ 10 m):")
    err32 = assert_equivariant(model, G, (x, edge_index), **check, atol=1e-4, rtol=1e-5)
    print(f"  SE2xR,   float32: {err32:.1e}   (output magnitude {y.abs().max():.1f})")
    # float64 needs float64 group elements: a float32 rotation cast up is only orthonormal to ~1e-8.
    err64 = assert_equivariant(model.double(), G, (x.double(), edge_index), **dict(check, g=g), atol=1e-10)
    print(f"  SE2xR,   float64: {err64:.1e}")

    # 4. The same code with the trivial group: no canonicalization, an ordinary GNN, not equivariant.
    torch.manual_seed(0)
    plain = SwarmNet(groups.Trivial()).to(device)
    err_plain = equivariance_error(plain, G, (x, edge_index), **check)
    print(f"  Trivial, float32: {err_plain:.1e}   <- same layers, no canonicalization: not equivariant")

    ok = err_plain > 1e-2  # the check above would have raised if the SE2xR model were not equivariant
    print("OK: the wrapped network is SE(2) x R equivariant" if ok else "unexpected: the plain network passed")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
