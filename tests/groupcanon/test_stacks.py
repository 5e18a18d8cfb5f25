"""Stacks of wrapped layers: equivariance end to end, training, gradients, dtypes/devices and no host syncs."""

from __future__ import annotations

import pytest
import torch
from gc_helpers import F32, F64, LAYER_TOL_F64, fixed_graph, graph_inputs, group_id, in_out_types
from hypothesis import given, settings
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode
from torch_geometric.nn import GATv2Conv, GCNConv, PointTransformerConv, TransformerConv

from groupcanon import Canonicalize, FieldType, frames
from groupcanon import groups as gg
from groupcanon.features import Point, Scalar, Vector
from groupcanon.testing import assert_equivariant, assert_invariant, equivariance_error

GROUPS = [gg.SE2xR(), gg.SE3(), gg.SO2()]


def _mlp(i, o, h=24):
    return nn.Sequential(nn.Linear(i, h), nn.SiLU(), nn.Linear(h, h), nn.SiLU(), nn.Linear(h, o))


class AttentionStack(nn.Module):
    """TransformerConv -> node-mode MLP -> GATv2Conv (with self loops), all wrapped."""

    def __init__(self, G):
        super().__init__()
        d = G.space_dim
        self.t_in, self.t_out = in_out_types(G)
        hid = FieldType(G, {"s": Scalar(8), "v": Vector(d, n=2), "p": Point(d)})
        self.conv1 = Canonicalize(G, self.t_in, hid)(TransformerConv(self.t_in.dim, hid.dim, heads=2, concat=False))
        self.mlp = Canonicalize(G, hid, hid)(_mlp(hid.dim, hid.dim))
        self.conv2 = Canonicalize(G, hid, self.t_out, self_loops=True)(
            GATv2Conv(hid.dim, self.t_out.dim, heads=2, concat=False, add_self_loops=False)
        )

    def forward(self, x, edge_index, frames):
        h = self.conv1(x, edge_index, frames=frames)
        h = self.mlp(h, frames=frames)
        return self.conv2(h, edge_index, frames=frames)


class PointStack(nn.Module):
    """PointTransformerConv (positions) -> MLP -> GCNConv (ego mode) -> invariant head: a CBF-like scalar."""

    def __init__(self, G):
        super().__init__()
        d = G.space_dim
        self.t_in, _ = in_out_types(G)
        hid = FieldType(G, {"s": Scalar(6), "v": Vector(d), "p": Point(d)})
        head = FieldType(G, [Scalar(1)])
        self.conv1 = Canonicalize(G, self.t_in, hid)(
            PointTransformerConv(self.t_in.dim, hid.dim, pos_nn=nn.Linear(d, hid.dim), add_self_loops=False)
        )
        self.mlp = Canonicalize(G, hid, hid)(_mlp(hid.dim, hid.dim))
        self.conv2 = Canonicalize(G, hid, hid)(GCNConv(hid.dim, hid.dim))
        self.head = Canonicalize(G, hid, head)(_mlp(hid.dim, 1))

    def forward(self, x, edge_index, frames, pos):
        h = self.conv1(x, edge_index, frames=frames, pos=pos)
        h = self.mlp(h, frames=frames)
        h = self.conv2(h, edge_index, frames=frames)
        return self.head(h, frames=frames)


class GeometricFrameStack(nn.Module):
    """SE2xR frames computed from the input itself (heading from a velocity, position from a point)."""

    def __init__(self):
        super().__init__()
        self.G = gg.SE2xR()
        self.inner = AttentionStack(self.G)

    def forward(self, x, edge_index):
        t = self.inner.t_in
        f = frames.se2xr_frame(t.get(x, "v"), t.get(x, "p"))
        return self.inner(x, edge_index, f)


def _build(cls, G, dtype=F64, seed=0):
    torch.manual_seed(seed)
    return cls(G).to(dtype)


# ------------------------------------------------------------------------------------------------ equivariance
@pytest.mark.parametrize("G", GROUPS, ids=group_id)
def test_attention_stack_equivariant(G):
    model = _build(AttentionStack, G)

    @given(inp=graph_inputs(G, model.t_in))
    def run(inp):
        assert_equivariant(
            model,
            G,
            (inp.x, inp.edge_index, inp.frames),
            in_types={0: model.t_in, 2: G},
            out_types=model.t_out,
            g=inp.g,
            atol=LAYER_TOL_F64,
        )

    run()


@pytest.mark.parametrize("G", GROUPS, ids=group_id)
def test_point_stack_invariant(G):
    model = _build(PointStack, G)

    @given(inp=graph_inputs(G, model.t_in, pos=True))
    def run(inp):
        assert_invariant(
            model,
            G,
            (inp.x, inp.edge_index, inp.frames, inp.pos),
            in_types={0: model.t_in, 2: G, 3: Point(G.space_dim)},
            g=inp.g,
            atol=LAYER_TOL_F64,
        )

    run()


def test_stack_with_frames_from_geometry_is_equivariant_without_frame_inputs():
    model = _build(lambda G: GeometricFrameStack(), None)
    G = model.G

    @settings(max_examples=max(5, settings.default.max_examples // 2))
    @given(inp=graph_inputs(G, model.inner.t_in))
    def run(inp):
        assert_equivariant(
            model,
            G,
            (inp.x, inp.edge_index),
            in_types={0: model.inner.t_in},
            out_types=model.inner.t_out,
            g=inp.g,
            atol=LAYER_TOL_F64,
        )

    run()


def test_stack_float32_equivariance():
    # float32: 1e-4 * (1 + max|output|)
    G = gg.SE2xR()
    model = _build(AttentionStack, G, F32)

    @settings(max_examples=max(5, settings.default.max_examples // 3))
    @given(inp=graph_inputs(G, model.t_in, dtype=F32))
    def run(inp):
        assert_equivariant(
            model,
            G,
            (inp.x, inp.edge_index, inp.frames),
            in_types={0: model.t_in, 2: G},
            out_types=model.t_out,
            g=inp.g,
            atol=1e-4,
            rtol=1e-4,
        )

    run()


# ------------------------------------------------------------------------------------------------ training
def _data(G, model_t_in, n=14, seed=0, dtype=F64):
    gen = torch.Generator().manual_seed(seed)
    ei = fixed_graph(n, seed=seed, degree=3)
    x = torch.randn(n, model_t_in.dim, generator=gen, dtype=dtype)
    fr = G.sample(n, generator=gen, dtype=dtype)
    pos = 3 * torch.randn(n, G.space_dim, generator=gen, dtype=dtype)
    return x, ei, fr, pos, gen


@pytest.mark.parametrize("cls", [AttentionStack, PointStack], ids=lambda c: c.__name__)
def test_training_reduces_loss_and_every_parameter_gets_a_gradient(cls):
    G = gg.SE2xR()
    model = _build(cls, G, F32)
    x, ei, fr, pos, gen = _data(G, model.t_in, dtype=F32)
    args = (x, ei, fr) if cls is AttentionStack else (x, ei, fr, pos)
    with torch.no_grad():
        target = torch.randn(model(*args).shape, generator=gen, dtype=F32)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for step in range(15):
        opt.zero_grad()
        loss = (model(*args) - target).pow(2).mean()
        loss.backward()
        if step == 0:
            for name, p in model.named_parameters():
                assert p.grad is not None, f"{name} got no gradient"
                assert torch.isfinite(p.grad).all(), f"{name} has a non-finite gradient"
                assert p.grad.abs().max() > 0, f"{name} has an all-zero gradient"
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.9 * losses[0], losses
    assert len(list(model.parameters())) >= 8


def test_gradients_flow_to_features_positions_and_frames():
    G = gg.SE2xR()
    model = _build(PointStack, G)
    x, ei, _, pos, _ = _data(G, model.t_in)
    heading = torch.randn(x.shape[0], 3, dtype=F64)
    x.requires_grad_(True)
    pos.requires_grad_(True)
    heading.requires_grad_(True)
    f = frames.se2xr_frame(heading, pos)  # frames depend on the positions too
    model(x, ei, f, pos).sum().backward()
    for name, t in (("x", x), ("pos", pos), ("heading", heading)):
        assert t.grad is not None and torch.isfinite(t.grad).all(), name
        assert t.grad.abs().max() > 0, name
    # frames use only the horizontal part of the heading: its z component gets no gradient
    assert torch.equal(heading.grad[:, 2], torch.zeros_like(heading.grad[:, 2]))


def test_gradient_of_invariant_output_is_equivariant():
    """d f / d pos of an invariant f transforms as a vector field: grad(g.inputs) = R(g) grad(inputs)."""
    G = gg.SE3()
    model = _build(PointStack, G)
    x, ei, fr, pos, gen = _data(G, model.t_in)
    g = G.sample(generator=gen, dtype=F64)

    def grad_pos(x, fr, pos):
        pos = pos.clone().requires_grad_(True)
        (gp,) = torch.autograd.grad(model(x, ei, fr, pos).sum(), pos)
        return gp

    g_ref = grad_pos(x, fr, pos)
    g_tr = grad_pos(model.t_in.act(g, x), G.compose(g, fr), G.transform(g, pos))
    assert (g_tr - G.rotate(g, g_ref)).abs().max() < 1e-10 * max(1.0, float(g_ref.abs().max()))
    assert g_ref.abs().max() > 1e-6


def test_backward_under_anomaly_detection_at_special_elements():
    """Frames at the near-singular angles (0, pi, 2 pi - 1e-11, ...), isolated nodes and a zero heading: the
    backward pass produces no NaN anywhere (anomaly mode raises on the first op that would)."""
    G = gg.SE2xR()
    model = _build(AttentionStack, G)
    sp = G.special_elements(dtype=F64)
    n = sp.shape[0]
    ei = fixed_graph(n, degree=2)
    ei = ei[:, ei[1] != 0]  # node 0 is isolated
    x = torch.randn(n, model.t_in.dim, dtype=F64, requires_grad=True)
    heading = sp[:, :2].clone()
    heading[1] = 0.0  # degenerate heading: planar_frame falls back to the x axis
    heading.requires_grad_(True)
    pos = sp[:, 2:].clone().requires_grad_(True)
    with torch.autograd.set_detect_anomaly(True):
        f = frames.se2xr_frame(heading, pos)
        model(x, ei, f).pow(2).sum().backward()
    for t in (x, heading, pos):
        assert torch.isfinite(t.grad).all()
    for p in model.parameters():
        assert torch.isfinite(p.grad).all()


# ------------------------------------------------------------------------------------------------ dtypes and devices
@pytest.mark.device
@pytest.mark.parametrize("dtype", [F32, F64], ids=["f32", "f64"])
@pytest.mark.parametrize("G", GROUPS, ids=group_id)
def test_runs_on_device_and_dtype(G, device, dtype):
    """On ``--device`` (conftest; cuda in benchmarks/gpu_check.sh): equivariant there, with gradients, and equal to
    the same stacks in float64 on the CPU (float32: 1e-4)."""
    dev = device
    torch.manual_seed(0)
    model = AttentionStack(G).to(device=dev, dtype=dtype)
    head = PointStack(G).to(device=dev, dtype=dtype)
    n = 12
    gen = torch.Generator().manual_seed(0)
    ei = fixed_graph(n).to(dev)
    x = torch.randn(n, model.t_in.dim, generator=gen, dtype=dtype).to(dev).requires_grad_(True)
    fr = G.sample(n, generator=gen, dtype=dtype).to(dev)
    pos = torch.randn(n, G.space_dim, generator=gen, dtype=dtype).to(dev)
    assert G.identity(2, dtype=dtype, device=dev).device.type == dev.type
    assert G.sample(2, dtype=dtype, device=dev).device.type == dev.type
    assert G.special_elements(dtype=dtype, device=dev).device.type == dev.type
    y = model(x, ei, fr)
    s = head(x, ei, fr, pos)
    assert y.device.type == dev.type and y.dtype == dtype and s.dtype == dtype
    (y.sum() + s.sum()).backward()
    assert x.grad.device.type == dev.type and torch.isfinite(x.grad).all()
    g = G.sample(2, generator=gen, dtype=dtype).to(dev)
    tol = dict(atol=LAYER_TOL_F64) if dtype == F64 else dict(atol=1e-4, rtol=1e-4)
    assert_equivariant(
        model, G, (x.detach(), ei, fr), in_types={0: model.t_in, 2: G}, out_types=model.t_out, g=g, **tol
    )
    reference = model.to(device="cpu", dtype=F64)(x.detach().cpu().double(), ei.cpu(), fr.cpu().double())
    torch.testing.assert_close(y.detach().cpu().double(), reference, **{"rtol": 0.0, **tol})


# ------------------------------------------------------------------------------------------------ no host syncs
class SyncSpy(TorchDispatchMode):
    """Records ops that copy a device value to the host (``.item()``, ``bool(tensor)``, data-dependent shapes)."""

    SYNC_OPS = ("_local_scalar_dense", "is_nonzero", "aten.item", "aten.nonzero", "aten.unique", "masked_select")

    def __init__(self):
        super().__init__()
        self.syncs: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = str(func)
        if any(k in name for k in self.SYNC_OPS):
            self.syncs.append(name)
        return func(*args, **(kwargs or {}))


def test_forward_and_backward_have_no_host_syncs():
    G = gg.SE3()
    model = _build(AttentionStack, G)
    point = _build(PointStack, G)
    x, ei, fr, pos, _ = _data(G, model.t_in)
    x.requires_grad_(True)
    with SyncSpy() as spy:
        y = model(x, ei, fr)
        s = point(x, ei, fr, pos)
        (y.sum() + s.sum()).backward()
    assert spy.syncs == [], spy.syncs


def test_sync_spy_detects_check_finite():
    """check_finite=True synchronizes (documented); the spy sees it, so the test above can fail."""
    G = gg.SE3()
    t_in, t_out = in_out_types(G)
    eq = Canonicalize(G, t_in, t_out, check_finite=True)(TransformerConv(t_in.dim, t_out.dim).double())
    x, ei, fr, _, _ = _data(G, t_in)
    with SyncSpy() as spy:
        eq(x, ei, frames=fr)
    assert spy.syncs


def test_wrapped_stack_error_is_tiny_but_raw_stack_error_is_not():
    """Sanity check of the stack test: replacing the frames by identities (i.e. no canonicalization of the
    transformed input) is not equivariant."""
    G = gg.SE2xR()
    model = _build(AttentionStack, G)
    x, ei, _, _, _ = _data(G, model.t_in)
    ident = G.identity(x.shape[0], dtype=F64)
    err = equivariance_error(model, G, (x, ei, ident), in_types={0: model.t_in}, out_types=model.t_out)
    assert err > 1e-3
