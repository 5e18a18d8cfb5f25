"""Canonicalization: make any graph layer equivariant by expressing each receiver's inputs in its own frame.

For a layer ``M`` and node frames ``g_v`` (group elements that transform with the scene, ``g_v -> g g_v``), the
wrapped layer computes, for every receiving node ``v``,

    f_v = rho_out(g_v) [ M( rho_in(g_v^-1) F ) ]_v                                   (canonicalization lemma)

where ``rho_in(g_v^-1) F`` is the whole one-hop neighbourhood of ``v`` expressed in ``v``'s frame. Because
``(g g_v)^-1 (g x) = g_v^-1 x``, the layer sees the same numbers whatever the global transform ``g``, so ``f`` is
equivariant whatever ``M`` is: ``M`` needs no constraint at all.

Different receivers see their neighbours in different frames, so the neighbourhoods are expanded:

* ``mode="pair"`` (layers that accept a ``(source, target)`` pair, e.g. TransformerConv, GATv2Conv, SAGEConv,
  GraphConv, EdgeConv, PointTransformerConv): one *source row per edge* ``u -> v`` holding
  ``rho_in(g_v^-1) x_u``, one target row per node holding ``rho_in(g_v^-1) x_v``, and edges ``e -> v``.
  The unmodified layer runs on this bipartite graph. Cost: the layer's source-side work grows from N to E rows.
* ``mode="ego"`` (layers that take a single node tensor, e.g. GCNConv): the disjoint union of ego graphs, with the
  N canonicalized receivers first and one copy of each source per edge after them; outputs are read from the first
  N rows. Degree-normalizing layers then see the ego graphs' degrees (see the guide).
* ``mode="node"`` (no edges: MLPs, heads): ``f_v = rho_out(g_v) M(rho_in(g_v^-1) x_v)``.

Only message receivers need frames. With a bipartite input ``x = (x_src, x_dst)``, frames are given for the
``x_dst`` rows only: senders such as goals or LiDAR hits carry no frame; they are seen in their receiver's frame.
"""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor, nn
from torch_geometric.utils import scatter

from .features import FieldType, Point
from .group import Group, check_element_shape
from .groups.trivial import Trivial

__all__ = ["Canonicalize", "CanonicalizedLayer", "globalize", "localize"]

_MODES = ("auto", "pair", "ego", "node")


def localize(field_type: FieldType, frames: Tensor, x: Tensor) -> Tensor:
    """Express world-frame features ``x`` ``(N, dim)`` in the node frames ``(N, *element_shape)``: ``rho(g^-1) x``."""
    return field_type.act(field_type.group.inverse(frames), x)


def globalize(field_type: FieldType, frames: Tensor, x: Tensor) -> Tensor:
    """Map features ``x`` ``(N, dim)`` from the node frames back to the world frame: ``rho(g) x``."""
    return field_type.act(frames, x)


def _as_pair(value, what: str):
    if isinstance(value, (tuple, list)):
        if len(value) != 2:
            raise ValueError(f"{what} given as a sequence must be a (source, target) pair, got {len(value)} items")
        return value[0], value[1], True
    return value, value, False


def _detect_mode(layer: nn.Module) -> str:
    """``"node"`` without an ``edge_index`` argument; else ``"pair"`` or ``"ego"`` from the annotation of ``x``
    (PyG annotates bipartite-capable layers with ``Union[Tensor, PairTensor]``). An unannotated ``x`` is an error,
    not a guess: the two modes feed the layer different graphs."""
    params = inspect.signature(layer.forward).parameters
    if "edge_index" not in params:
        return "node"
    x = params.get("x")
    if x is None or x.annotation is inspect.Parameter.empty:
        raise ValueError(
            f"cannot tell from {type(layer).__name__}.forward's signature whether it takes a (source, target) "
            "pair of node tensors: its x is not annotated. Pass Canonicalize(..., mode='pair') for a bipartite-"
            "capable layer (e.g. TransformerConv, GATConv) or mode='ego' for a layer of one node tensor (GCNConv)"
        )
    annotation = str(x.annotation)
    return "pair" if any(k in annotation for k in ("Pair", "Tuple", "tuple")) else "ego"


class Canonicalize:
    """Factory: ``Canonicalize(G, in_type=..., out_type=...)(layer)`` returns an equivariant ``nn.Module``.

    Args:
        group: the symmetry group.
        in_type: FieldType of the node features, or a ``(source_type, target_type)`` pair for bipartite inputs.
        out_type: FieldType of the layer's output rows.
        edge_type: FieldType of ``edge_attr`` if it is *typed* (e.g. a relative position as a ``Vector``); it is
            then expressed in the receiver's frame. ``None`` (default): ``edge_attr`` is invariant, passed as is.
        pos_type: FeatureType/FieldType of ``pos`` (default ``Point(group.space_dim)``) for layers with positions.
        mode: ``"pair"``, ``"ego"``, ``"node"`` or ``"auto"`` (from the layer's ``forward`` signature).
        self_loops: pair mode only: add one edge per receiver from its own canonicalized features (the
            self loop that GATv2Conv / PointTransformerConv would add by index, which is wrong on the expanded
            graph; construct those layers with ``add_self_loops=False`` and use this instead). A loop's
            ``edge_attr`` is the mean of the receiver's incoming attributes, as PyG's ``fill_value="mean"``.
        check_finite: raise if ``x``, ``frames`` or ``pos`` hold NaN or inf. Off by default because the check
            synchronizes with the device; without it non-finite inputs propagate (never silently replaced).
        check_frames: raise a ``ValueError`` if a frame is not a group element up to ``frame_atol``
            (:meth:`Group.check_member`: a non-unit planar rotation, a non-orthogonal or reflected rotation
            matrix, NaN or inf), and if ``edge_index`` points outside the node range. Off by default (it
            synchronizes with the device); without it such frames give wrong, non-equivariant outputs.
        frame_atol: the tolerance of ``check_frames``.

    Always checked (free: shapes and dtypes only): the element shape of ``frames``, one frame per receiving node,
    ``edge_index`` ``(2, E)`` long, and that ``frames`` and ``x`` have the same floating dtype.
    """

    def __init__(
        self,
        group: Group,
        in_type: FieldType | Sequence[FieldType],
        out_type: FieldType,
        *,
        edge_type: FieldType | None = None,
        pos_type=None,
        mode: str = "auto",
        self_loops: bool = False,
        check_finite: bool = False,
        check_frames: bool = False,
        frame_atol: float = 1e-4,
    ):
        if not isinstance(group, Group):
            raise TypeError(f"Canonicalize needs a groupcanon Group, got {type(group).__name__}")
        src_type, dst_type, _ = _as_pair(in_type, "in_type")
        for name, t in (("in_type", src_type), ("in_type", dst_type), ("out_type", out_type)):
            if not isinstance(t, FieldType):
                raise TypeError(f"{name} must be a FieldType, got {type(t).__name__}")
            if t.group != group:
                raise ValueError(f"{name} is a FieldType of {t.group}, but Canonicalize was given {group}")
        if edge_type is not None and (not isinstance(edge_type, FieldType) or edge_type.group != group):
            raise ValueError("edge_type must be a FieldType of the same group (or None for invariant edge_attr)")
        if mode not in _MODES:
            raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
        if pos_type is None and group.space_dim is not None:
            pos_type = FieldType(group, [Point(group.space_dim)])
        elif pos_type is not None and not isinstance(pos_type, FieldType):
            pos_type = FieldType(group, [pos_type])
        self.group = group
        self.src_type, self.dst_type = src_type, dst_type
        self.out_type = out_type
        self.edge_type = edge_type
        self.pos_type = pos_type
        self.mode = mode
        self.self_loops = bool(self_loops)
        self.check_finite = bool(check_finite)
        if not (isinstance(frame_atol, (int, float)) and frame_atol >= 0):
            raise ValueError(f"frame_atol must be a number >= 0, got {frame_atol!r}")
        self.check_frames = bool(check_frames)
        self.frame_atol = float(frame_atol)

    def __call__(self, layer: nn.Module) -> CanonicalizedLayer:
        if not isinstance(layer, nn.Module):
            raise TypeError(f"Canonicalize wraps a torch.nn.Module, got {type(layer).__name__}")
        return CanonicalizedLayer(layer, self)


class CanonicalizedLayer(nn.Module):
    """An equivariant wrapper around an unmodified layer (built by :class:`Canonicalize`).

    Call as ``eq(x, edge_index, *, frames, pos=None, edge_attr=None, **kwargs)`` (``frames`` keyword-only: PyG
    layers take ``edge_attr`` third):

    * ``x``: ``(N, in_dim)`` or a bipartite pair ``(x_src (N_src, in_dim), x_dst (N_dst, in_dim))``.
    * ``edge_index``: ``(2, E)`` long, rows (source, target), targets index ``x_dst``.
    * ``frames``: ``(N_dst, *group.element_shape)``: one frame per receiving node.
    * ``pos``: optional positions ``(N, d)`` or a pair, transformed with ``pos_type``.
    * ``edge_attr``: optional ``(E, edge_dim)``, invariant unless ``edge_type`` was given.
    * other keyword arguments are passed to the layer unchanged: they must be invariant (e.g. ``edge_weight``).

    Returns ``(N_dst, out_type.dim)`` in the world frame; if the layer returns a tuple, the first item is mapped
    and the rest (e.g. attention weights, which are invariant) is returned beside it. With
    ``return_attention_weights=True`` the returned ``edge_index`` is the caller's (plus ``(i, i)`` per node when
    ``self_loops``), row for row with the weights, not the internal canonicalized graph's.
    In ``mode="node"`` call as ``eq(x, frames=frames)``.
    """

    def __init__(self, layer: nn.Module, spec: Canonicalize):
        super().__init__()
        self.layer = layer
        self.spec = spec
        self.mode = _detect_mode(layer) if spec.mode == "auto" else spec.mode
        # trivial group: run the raw layer as is (but not when self_loops must add edges the raw layer lacks)
        # (ego mode keeps the ego-graph path so that degree-normalizing layers see the same graph for every group)
        self._identity = isinstance(spec.group, Trivial) and (
            self.mode == "node" or (self.mode == "pair" and not spec.self_loops)
        )
        if self.mode == "pair" and getattr(layer, "add_self_loops", False):
            raise ValueError(
                f"{type(layer).__name__} adds self loops by node index, which connects the wrong rows of the "
                "edge-expanded bipartite graph. Construct it with add_self_loops=False and pass "
                "Canonicalize(..., self_loops=True) for the same semantics."
            )
        if self.mode != "pair" and spec.src_type != spec.dst_type:
            raise ValueError(f"separate source/target in_types need mode='pair', got mode={self.mode!r}")

    @property
    def group(self) -> Group:
        return self.spec.group

    def reset_parameters(self) -> None:
        """The wrapped layer's ``reset_parameters()`` (a wrapper has no parameters of its own)."""
        if not hasattr(self.layer, "reset_parameters"):
            raise AttributeError(f"{type(self.layer).__name__} has no reset_parameters()")
        self.layer.reset_parameters()

    def extra_repr(self) -> str:
        s = self.spec
        return f"group={s.group}, mode={self.mode}, in={s.dst_type.dim}, out={s.out_type.dim}"

    # ------------------------------------------------------------------ validation
    def _check_frames(self, frames: Tensor, n_dst: int, x: Tensor) -> None:
        check_element_shape(self.group, frames, "frames")
        batch = self.group.batch_shape(frames)
        if len(batch) != 1 or batch[0] != n_dst:
            raise ValueError(
                f"frames have batch shape {tuple(batch)}, but the graph has {n_dst} receiving nodes: "
                f"pass one frame per node of x (per x_dst row for bipartite input), "
                f"shape ({n_dst}, {', '.join(map(str, self.group.element_shape))})"
            )
        if (
            self.group.element_numel
            and frames.dtype != x.dtype
            and frames.is_floating_point()
            and x.is_floating_point()
        ):
            raise TypeError(f"frames have dtype {frames.dtype} but x has {x.dtype}: cast with frames.to(x.dtype)")
        if self.spec.check_frames:
            self.group.check_member(frames, self.spec.frame_atol, "frames")

    @staticmethod
    def _check_index_range(edge_index: Tensor, n_src: int, n_dst: int) -> None:
        """Raise a ``ValueError`` naming ``edge_index`` if a source is outside ``[0, n_src)`` or a target outside
        ``[0, n_dst)`` (a device synchronization: run only on request or after an indexing error)."""
        if edge_index.numel() == 0:
            return
        for row, n, what in ((0, n_src, "source"), (1, n_dst, "target")):
            lo, hi = int(edge_index[row].min()), int(edge_index[row].max())
            if lo < 0 or hi >= n:
                raise ValueError(
                    f"edge_index row {row} ({what}s) holds node indices in [{lo}, {hi}], outside [0, {n}) "
                    f"(the {what} node count)"
                )

    @staticmethod
    def _check_edge_index(edge_index: Tensor) -> None:
        if not isinstance(edge_index, Tensor) or edge_index.dim() != 2 or edge_index.shape[0] != 2:
            shape = tuple(edge_index.shape) if isinstance(edge_index, Tensor) else type(edge_index).__name__
            raise ValueError(f"edge_index must be a (2, E) tensor, got {shape}")
        if edge_index.dtype != torch.long:
            raise ValueError(f"edge_index must have dtype torch.long, got {edge_index.dtype}")

    def _check_finite(self, **tensors) -> None:
        for name, t in tensors.items():
            if t is not None and not bool(torch.isfinite(t).all()):
                raise ValueError(f"{name} contains NaN or inf")

    def _finish(self, out: Any, frames: Tensor) -> Any:
        rest = ()
        if isinstance(out, tuple):
            out, *rest = out
        if out.shape[-1] != self.spec.out_type.dim:
            raise ValueError(
                f"{type(self.layer).__name__} returned {out.shape[-1]} channels, but out_type has dim "
                f"{self.spec.out_type.dim}"
            )
        y = self.spec.out_type.act(frames, out)
        return (y, *rest) if rest else y

    # ------------------------------------------------------------------ forward
    def forward(self, x, edge_index: Tensor | None = None, *, frames: Tensor | None = None, **kwargs):
        if frames is None:
            raise TypeError("frames are required: eq(x, edge_index, frames=frames)")
        spec = self.spec
        if self.mode == "node":
            if edge_index is not None:
                raise TypeError("mode='node' layers take no edge_index: call eq(x, frames=frames)")
            spec.dst_type.check(x, "x")
            self._check_frames(frames, x.shape[0], x)
            if spec.check_finite:
                self._check_finite(x=x, frames=frames)
            if self._identity:
                return self.layer(x, **kwargs)
            return self._finish(self.layer(localize(spec.dst_type, frames, x), **kwargs), frames)

        if edge_index is None:
            raise TypeError("edge_index is required for graph layers")
        self._check_edge_index(edge_index)
        x_src, x_dst, bipartite = _as_pair(x, "x")
        spec.src_type.check(x_src, "x (source)" if bipartite else "x")
        spec.dst_type.check(x_dst, "x (target)" if bipartite else "x")
        n_dst = x_dst.shape[0]
        self._check_frames(frames, n_dst, x_dst)
        if spec.check_frames:
            self._check_index_range(edge_index, x_src.shape[0], n_dst)
        pos = kwargs.pop("pos", None)
        edge_attr = kwargs.pop("edge_attr", None)
        num_edges = edge_index.shape[1]
        if edge_attr is not None and edge_attr.shape[0] != num_edges:
            raise ValueError(f"edge_attr has {edge_attr.shape[0]} rows, edge_index has {num_edges} edges")
        if edge_attr is not None and spec.edge_type is not None:
            spec.edge_type.check(edge_attr, "edge_attr")
        if spec.check_finite:
            p_src, p_dst, _ = _as_pair(pos, "pos")
            self._check_finite(x_src=x_src, x_dst=x_dst, frames=frames, pos_src=p_src, pos_dst=p_dst)

        if self._identity:  # trivial group: every action is the identity; run the raw layer as is
            if pos is not None:
                kwargs["pos"] = pos
            if edge_attr is not None:
                kwargs["edge_attr"] = edge_attr
            return self.layer(x=x, edge_index=edge_index, **kwargs)

        if self.mode == "ego" and bipartite:
            raise ValueError("mode='ego' takes a single node tensor x, not a (source, target) pair")
        try:
            if self.mode == "pair":
                out = self._forward_pair(x_src, x_dst, edge_index, frames, pos, edge_attr, kwargs)
            else:
                out = self._forward_ego(x_dst, edge_index, frames, pos, edge_attr, kwargs)
        except (IndexError, RuntimeError):
            self._check_index_range(edge_index, x_src.shape[0], n_dst)  # a clear error if that was the cause
            raise
        if kwargs.get("return_attention_weights") and isinstance(out, tuple) and len(out) == 2:
            out = (out[0], self._callers_attention(out[1], edge_index, n_dst))
        return self._finish(out, frames)

    def _callers_attention(self, weights, edge_index: Tensor, n_dst: int):
        """``(edge_index, alpha)`` of the internal graph -> the same weights on the caller's ``edge_index`` (with
        the self loops appended when ``self_loops``): the internal graph lists the caller's edges in order, then
        (pair mode, ``self_loops``) one loop per receiver."""
        if not (isinstance(weights, tuple) and len(weights) == 2 and isinstance(weights[0], Tensor)):
            return weights  # a sparse adjacency or another format: left as the layer returned it
        internal, alpha = weights
        ei = edge_index
        if self.mode == "pair" and self.spec.self_loops:
            nodes = torch.arange(n_dst, device=ei.device)
            ei = torch.cat((ei, torch.stack((nodes, nodes))), dim=1)
        if internal.shape[1] != ei.shape[1] or not torch.equal(internal[1], ei[1]):
            return weights  # the layer changed the graph (e.g. its own self loops): report what it returned
        return ei, alpha

    def _edge_inputs(self, inv_e: Tensor, edge_attr: Tensor | None, kwargs: dict) -> None:
        if edge_attr is not None:
            et = self.spec.edge_type
            kwargs["edge_attr"] = edge_attr if et is None else et.act(inv_e, edge_attr)

    def _pos_inputs(self, pos, src: Tensor, inv: Tensor, inv_e: Tensor):
        if pos is None:
            return None
        if self.spec.pos_type is None:
            raise ValueError(f"{self.group} has no action on positions: give pos_type to Canonicalize")
        p_src, p_dst, _ = _as_pair(pos, "pos")
        pt = self.spec.pos_type
        pt.check(p_src, "pos")
        pt.check(p_dst, "pos")
        return pt.act_gathered(inv_e, p_src, src), pt.act(inv, p_dst)

    def _forward_pair(self, x_src, x_dst, edge_index, frames, pos, edge_attr, kwargs):
        spec = self.spec
        src, dst = edge_index[0], edge_index[1]
        inv = self.group.inverse(frames)  # N_dst inverses, gathered per edge
        inv_e = inv.index_select(0, dst)
        xs = spec.src_type.act_gathered(inv_e, x_src, src)  # (E, in): each source seen in its receiver's frame
        xd = spec.dst_type.act(inv, x_dst)  # (N_dst, in)
        num_edges, n_dst = src.shape[0], xd.shape[0]
        rows = torch.arange(num_edges, device=src.device)
        pos_pair = self._pos_inputs(pos, src, inv, inv_e)
        self._edge_inputs(inv_e, edge_attr, kwargs)
        if spec.self_loops:
            nodes = torch.arange(n_dst, device=src.device)
            rows = torch.cat((rows, num_edges + nodes))
            edge_dst, dst = dst, torch.cat((dst, nodes))
            # the loop carries the receiver's own features, localized with their own (target) type: acting with
            # the source type on them would not be equivariant when the two types differ
            if xd.shape[-1] != xs.shape[-1]:
                raise ValueError(
                    f"self_loops=True feeds each receiver's own features as a source row, but source rows have "
                    f"{xs.shape[-1]} channels and target rows {xd.shape[-1]}"
                )
            xs = torch.cat((xs, xd))
            if pos_pair is not None:
                pos_pair = (torch.cat((pos_pair[0], pos_pair[1])), pos_pair[1])
            if "edge_attr" in kwargs:
                # like PyG's add_self_loops(fill_value="mean"): the mean of the receiver's incoming attributes
                # (already in its frame, so the fill is equivariant); zeros for receivers without edges
                ea = kwargs["edge_attr"]
                loop_attr = scatter(ea, edge_dst, dim=0, dim_size=n_dst, reduce="mean")
                kwargs["edge_attr"] = torch.cat((ea, loop_attr))
        if pos_pair is not None:
            kwargs["pos"] = pos_pair
        return self.layer(x=(xs, xd), edge_index=torch.stack((rows, dst)), **kwargs)

    def _forward_ego(self, x, edge_index, frames, pos, edge_attr, kwargs):
        spec = self.spec
        src, dst = edge_index[0], edge_index[1]
        n = x.shape[0]
        inv = self.group.inverse(frames)
        inv_e = inv.index_select(0, dst)
        x_union = torch.cat((spec.dst_type.act(inv, x), spec.src_type.act_gathered(inv_e, x, src)))  # (N + E, in)
        rows = n + torch.arange(src.shape[0], device=src.device)
        pos_pair = self._pos_inputs(pos, src, inv, inv_e)
        if pos_pair is not None:
            kwargs["pos"] = torch.cat((pos_pair[1], pos_pair[0]))
        self._edge_inputs(inv_e, edge_attr, kwargs)
        out = self.layer(x=x_union, edge_index=torch.stack((rows, dst)), **kwargs)
        if isinstance(out, tuple):
            return (out[0][:n], *out[1:])
        return out[:n]
