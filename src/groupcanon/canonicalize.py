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

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor, nn
from torch_geometric.utils import scatter

from .features import FeatureType, Point
from .field_type import FieldType
from .group import Group, require_group
from .groups.trivial import Trivial
from .input_checks import (
    _as_pair,
    _check_action_args,
    _check_declared_widths,
    _check_edge_attr,
    _check_edge_index,
    _check_finite,
    _check_frames,
    _check_index_range,
    _check_layer_dtypes,
    _check_pos,
    _check_rows,
    _detect_mode,
    _named_inputs,
)

__all__ = ["Canonicalize", "CanonicalizedLayer", "globalize", "localize"]

_MODES = ("auto", "pair", "ego", "node")


def _localize(field_type: FieldType, frames: Tensor, x: Tensor) -> Tensor:
    return field_type.act(field_type.group.inverse(frames), x)


def localize(field_type: FieldType, frames: Tensor, x: Tensor) -> Tensor:
    """Express world-frame features ``x`` ``(N, dim)`` in the node frames ``(N, *element_shape)``: ``rho(g^-1) x``."""
    _check_action_args("localize", field_type, frames, x)
    return _localize(field_type, frames, x)


def globalize(field_type: FieldType, frames: Tensor, x: Tensor) -> Tensor:
    """Map features ``x`` ``(N, dim)`` from the node frames back to the world frame: ``rho(g) x``."""
    _check_action_args("globalize", field_type, frames, x)
    return field_type.act(frames, x)


class Canonicalize:
    """Factory: ``Canonicalize(G, in_type=..., out_type=...)(layer)`` returns an equivariant ``nn.Module``.

    Args:
        group: the symmetry group.
        in_type: FieldType of the node features, or a ``(source_type, target_type)`` pair for bipartite inputs.
        out_type: FieldType of the layer's output rows.
        edge_type: FieldType of ``edge_attr`` if it is *typed* (e.g. a relative position as a ``Vector``); it is
            then expressed in the receiver's frame. ``None`` (default): ``edge_attr`` is invariant, passed as is.
        pos_type: FeatureType/FieldType of ``pos`` for layers with positions. Default ``Point(group.space_dim)``;
            for a group that acts on every dimension and has no ``space_dim`` (``Trivial``), ``Point(d)`` with ``d``
            the width of the ``pos`` given, so that switching a model to ``Trivial()`` needs no other change.
        mode: ``"pair"``, ``"ego"``, ``"node"`` or ``"auto"`` (from the layer's ``forward`` signature).
        self_loops: pair mode only: add one edge per receiver from its own canonicalized features (the
            self loop that GATv2Conv / PointTransformerConv would add by index, which is wrong on the expanded
            graph; construct those layers with ``add_self_loops=False`` and use this instead). A loop's
            ``edge_attr`` is the mean of the receiver's incoming attributes, as PyG's ``fill_value="mean"``.
        check_finite: raise a ``ValueError`` naming the input if any floating-point input holds NaN or inf:
            ``x``, ``frames``, ``pos``, ``edge_attr`` and the floating tensors among the other keyword arguments
            (e.g. ``edge_weight``). Off by default because the check synchronizes with the device (once per call);
            without it non-finite inputs propagate (never silently replaced).
        check_frames: raise a ``ValueError`` if a frame is not a group element up to ``frame_atol``
            (:meth:`Group.check_member`: a non-unit planar rotation, a non-orthogonal or reflected rotation
            matrix, NaN or inf), and if ``edge_index`` points outside the node range. Off by default (it
            synchronizes with the device); without it such frames give wrong, non-equivariant outputs.
        frame_atol: the tolerance of ``check_frames``.

    Checked when a layer is wrapped: the FieldTypes' widths against those the layer declares (PyG's ``in_channels``
    and ``out_channels``, times ``heads`` when ``concat=True``; torch's ``in_features`` / ``out_features``).
    Always checked per call (free: shapes and dtypes only): ``x`` ``(N, in_type.dim)`` (no extra batch dimension),
    the element shape of ``frames``, one frame per receiving node, ``edge_index`` ``(2, E)`` long, the shapes of
    ``pos`` and ``edge_attr``, and that ``frames``, ``pos`` and a typed ``edge_attr`` have the floating dtype of
    ``x``. If the layer itself fails, the wrapper looks for the usual causes (an ``edge_index`` out of range, an
    input whose dtype differs from the layer's parameters) and raises an error naming that input instead.
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
        require_group(group, "Canonicalize(group, ...): group")
        src_type, dst_type, _ = _as_pair(in_type, "in_type")
        for name, t in (("in_type", src_type), ("in_type", dst_type), ("out_type", out_type), ("edge_type", edge_type)):
            if t is None and name == "edge_type":
                continue
            if not isinstance(t, FieldType):
                raise TypeError(f"Canonicalize: {name} must be a FieldType, got {type(t).__name__}")
            if t.group != group:
                raise ValueError(f"{name} is a FieldType of {t.group}, but Canonicalize was given {group}")
        if mode not in _MODES:
            raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
        if pos_type is None and group.space_dim is not None:
            pos_type = FieldType(group, [Point(group.space_dim)])
        elif isinstance(pos_type, FeatureType):
            pos_type = FieldType(group, [pos_type])
        elif pos_type is not None and not isinstance(pos_type, FieldType):
            raise TypeError(f"Canonicalize: pos_type must be a FeatureType or FieldType, got {type(pos_type).__name__}")
        elif pos_type is not None and pos_type.group != group:
            raise ValueError(f"pos_type is a FieldType of {pos_type.group}, but Canonicalize was given {group}")
        self.group = group
        self.src_type, self.dst_type = src_type, dst_type
        self.out_type = out_type
        self.edge_type = edge_type
        self.pos_type = pos_type
        self._pos_types: dict[int, FieldType] = {}  # pos_type=None: Point(d) per width d, for groups of any dimension
        self.mode = mode
        self.self_loops = bool(self_loops)
        self.check_finite = bool(check_finite)
        if not (isinstance(frame_atol, (int, float)) and frame_atol >= 0):
            raise ValueError(f"frame_atol must be a number >= 0, got {frame_atol!r}")
        self.check_frames = bool(check_frames)
        self.frame_atol = float(frame_atol)

    def pos_field(self, pos: Tensor) -> FieldType:
        """The FieldType of positions ``pos`` ``(N, d)``: ``pos_type``, or when none was given and the group has no
        ``space_dim`` but acts on every dimension (``Trivial``), ``Point(d)`` with ``d = pos.shape[-1]``."""
        if self.pos_type is not None:
            return self.pos_type
        d = pos.shape[-1] if isinstance(pos, Tensor) and pos.dim() else 0
        if d < 1 or not self.group.acts_on_space(d):
            raise ValueError(f"{self.group} has no action on positions: give pos_type to Canonicalize")
        pt = self._pos_types.get(d)
        if pt is None:
            pt = self._pos_types[d] = FieldType(self.group, [Point(d)])
        return pt

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
        _check_declared_widths(layer, spec)

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

    def _finish(self, out: Any, frames: Tensor) -> Any:
        rest = ()
        if isinstance(out, tuple) and out:
            out, *rest = out
        if not isinstance(out, Tensor):
            what = f"a tuple whose first item is {type(out).__name__}" if rest else type(out).__name__
            raise TypeError(
                f"{type(self.layer).__name__} returned {what}; a wrapped layer must return a tensor of out_type's "
                f"{self.spec.out_type.dim} channels, or a tuple whose first item is one"
            )
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
        if self.mode == "node":
            return self._forward_node(x, edge_index, frames, kwargs)
        spec = self.spec
        if edge_index is None:
            raise TypeError("edge_index is required for graph layers")
        _check_edge_index(edge_index)
        x_src, x_dst, bipartite = _as_pair(x, "x")
        names = ("x (source)", "x (target)") if bipartite else ("x", "x")
        _check_rows(spec.src_type, x_src, names[0])
        _check_rows(spec.dst_type, x_dst, names[1])
        n_dst = x_dst.shape[0]
        _check_frames(spec, frames, n_dst, x_dst)
        if spec.check_frames:
            _check_index_range(edge_index, x_src.shape[0], n_dst)
        pos = kwargs.pop("pos", None)
        edge_attr = kwargs.pop("edge_attr", None)
        if pos is not None:
            _check_pos(spec, pos, x_dst)
        if edge_attr is not None:
            _check_edge_attr(spec, edge_attr, edge_index.shape[1], x_dst)
        if spec.check_finite:
            _check_finite(_named_inputs(x, frames, pos, edge_attr, kwargs))
        if self.mode == "ego" and bipartite:
            raise ValueError("mode='ego' takes a single node tensor x, not a (source, target) pair")

        try:
            if self._identity:  # trivial group: every action is the identity; run the raw layer as is
                if pos is not None:
                    kwargs["pos"] = pos
                if edge_attr is not None:
                    kwargs["edge_attr"] = edge_attr
                return self.layer(x=x, edge_index=edge_index, **kwargs)
            if self.mode == "pair":
                out = self._forward_pair(x_src, x_dst, edge_index, frames, pos, edge_attr, kwargs)
            else:
                out = self._forward_ego(x_dst, edge_index, frames, pos, edge_attr, kwargs)
        except (IndexError, RuntimeError) as err:  # a clear error if the cause is one of these
            _check_index_range(edge_index, x_src.shape[0], n_dst)
            _check_layer_dtypes(self.layer, _named_inputs(x, frames, pos, edge_attr, kwargs), err)
            raise
        if kwargs.get("return_attention_weights") and isinstance(out, tuple) and len(out) == 2:
            out = (out[0], self._callers_attention(out[1], edge_index, n_dst))
        return self._finish(out, frames)

    def _forward_node(self, x, edge_index, frames: Tensor, kwargs: dict):
        """``mode="node"``: ``f_v = rho_out(g_v) M(rho_in(g_v^-1) x_v)`` row by row."""
        if edge_index is not None:
            raise TypeError("mode='node' layers take no edge_index: call eq(x, frames=frames)")
        spec = self.spec
        _check_rows(spec.dst_type, x, "x")
        _check_frames(spec, frames, x.shape[0], x)
        if spec.check_finite:
            _check_finite(_named_inputs(x, frames, None, None, kwargs))
        try:
            if self._identity:
                return self.layer(x, **kwargs)
            out = self.layer(_localize(spec.dst_type, frames, x), **kwargs)
        except RuntimeError as err:
            _check_layer_dtypes(self.layer, _named_inputs(x, frames, None, None, kwargs), err)
            raise
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
        p_src, p_dst, _ = _as_pair(pos, "pos")  # checked in forward
        pt = self.spec.pos_field(p_dst)
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
