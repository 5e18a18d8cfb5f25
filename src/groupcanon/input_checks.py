"""Input checks of :class:`~groupcanon.canonicalize.Canonicalize` and its wrapped layers.

Checked here: the FieldTypes' widths against those a layer declares (when it is wrapped), the arguments of
``localize`` / ``globalize``, and per call the shapes and dtypes of ``x``, ``frames``, ``edge_index``, ``pos`` and
``edge_attr``. These are cheap shape/dtype checks with no device synchronization; the opt-in ones
(``check_finite``, ``check_frames``: finite values, frames in the group, ``edge_index`` in range) and the diagnosis
after a layer failure read values and so synchronize with the device.
"""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from typing import Any, Protocol

import torch
from torch import Tensor, nn

from .field_type import FieldType
from .group import Group, check_element_shape


class _Spec(Protocol):
    """What the checks read of a :class:`~groupcanon.canonicalize.Canonicalize` (typed structurally: importing it
    here, even under ``TYPE_CHECKING``, would close an import cycle)."""

    group: Group
    src_type: FieldType
    dst_type: FieldType
    out_type: FieldType
    edge_type: FieldType | None
    check_frames: bool
    frame_atol: float

    def pos_field(self, pos: Tensor) -> FieldType: ...


def _check_action_args(fn: str, field_type, frames, x) -> None:
    """Raise a ``TypeError`` / ``ValueError`` naming ``fn``'s argument (``field_type``, ``frames`` or ``x``)."""
    if not isinstance(field_type, FieldType):
        raise TypeError(f"{fn}() argument field_type must be a FieldType, got {type(field_type).__name__}")
    check_element_shape(field_type.group, frames, f"{fn}() argument frames")
    field_type.check(x, f"{fn}() argument x")


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


def _declared_out_width(layer: nn.Module) -> tuple[int, str] | None:
    """The output width ``layer`` declares and how, or ``None``: PyG's ``out_channels`` (times ``heads`` when
    ``concat=True``, times ``len(powers)`` for MixHopConv), torch's ``out_features``; unset or lazy (< 1) is None."""
    for attr in ("out_channels", "out_features"):
        value = getattr(layer, attr, None)
        if isinstance(value, int) and value > 0:
            width, how = value, f"{attr}={value}"
            heads = getattr(layer, "heads", None)
            if getattr(layer, "concat", False) is True and isinstance(heads, int) and heads != 1:
                width, how = width * heads, f"{how} x heads={heads} (concat=True)"
            powers = getattr(layer, "powers", None)
            if isinstance(powers, (list, tuple)) and len(powers) != 1:
                width, how = width * len(powers), f"{how} x {len(powers)} powers"
            return width, how
    return None


def _check_declared_widths(layer: nn.Module, spec: _Spec) -> None:
    """Raise a ``ValueError`` if the FieldTypes' widths differ from those ``layer`` declares: PyG's ``in_channels``
    (an int, or a ``(source, target)`` pair; ``-1`` for lazy is not checked) and output width
    (:func:`_declared_out_width`), torch's ``in_features`` / ``out_features``. Layers that declare no widths (an
    ``nn.Sequential``, ``EdgeConv``) are not checked here; a wrong output width still fails at the first call."""
    name = type(layer).__name__
    for attr in ("in_channels", "in_features"):
        declared = getattr(layer, attr, None)
        if declared is None:
            continue
        pair = isinstance(declared, (tuple, list)) and len(declared) == 2
        widths = tuple(declared) if pair else (declared, declared)
        for width, ft, side in zip(widths, (spec.src_type, spec.dst_type), ("source", "target")):
            if isinstance(width, int) and width > 0 and width != ft.dim:
                what = "in_type" if spec.src_type is spec.dst_type else f"in_type ({side})"
                raise ValueError(
                    f"{name} declares {attr}={declared!r}, but {what} {ft!r} has dim {ft.dim}: construct the "
                    "layer with the FieldType's width"
                )
        break
    out = _declared_out_width(layer)
    if out is not None and out[0] != spec.out_type.dim:
        raise ValueError(
            f"{name} declares {out[1]}, i.e. {out[0]} output channels, but out_type {spec.out_type!r} has dim "
            f"{spec.out_type.dim}: construct the layer with the FieldType's width"
        )


def _named_inputs(x, frames, pos, edge_attr, kwargs: dict) -> list[tuple[str, Any]]:
    """The call's inputs as ``(name, value)`` pairs, named as the caller passed them (``x (source)`` for the
    source part of a pair), for :func:`_check_finite` and the layer-failure diagnosis."""
    named = []
    for what, value in (("x", x), ("frames", frames), ("pos", pos), ("edge_attr", edge_attr)):
        if isinstance(value, (tuple, list)) and len(value) == 2:
            named += [(f"{what} (source)", value[0]), (f"{what} (target)", value[1])]
        elif value is not None:
            named.append((what, value))
    return named + list(kwargs.items())


def _check_rows(ft: FieldType, t, what: str, rows: str = "N") -> None:
    """Raise a clear error naming ``what`` unless ``t`` is a tensor ``(rows, ft.dim)``: one row per node (or edge),
    no extra batch dimension (batch graphs into one disjoint graph instead, as ``torch_geometric``'s ``Batch``)."""
    ft.check(t, what)
    if t.dim() != 2:
        raise ValueError(
            f"{what} has shape {tuple(t.shape)}, expected ({rows}, {ft.dim}): one row per "
            f"{'edge' if rows == 'E' else 'node'} and no batch dimension (put the graphs of a batch into one "
            "disjoint graph, as torch_geometric's Batch does)"
        )


def _check_frames(spec: _Spec, frames: Tensor, n_dst: int, x: Tensor) -> None:
    group = spec.group
    check_element_shape(group, frames, "frames")
    batch = group.batch_shape(frames)
    if len(batch) != 1 or batch[0] != n_dst:
        raise ValueError(
            f"frames have batch shape {tuple(batch)}, but the graph has {n_dst} receiving nodes: "
            f"pass one frame per node of x (per x_dst row for bipartite input), "
            f"shape ({n_dst}, {', '.join(map(str, group.element_shape))})"
        )
    if group.element_numel and frames.dtype != x.dtype and frames.is_floating_point() and x.is_floating_point():
        raise TypeError(f"frames have dtype {frames.dtype} but x has {x.dtype}: cast with frames.to(x.dtype)")
    if spec.check_frames:
        group.check_member(frames, spec.frame_atol, "frames")


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


def _check_edge_index(edge_index: Tensor) -> None:
    if not isinstance(edge_index, Tensor) or edge_index.dim() != 2 or edge_index.shape[0] != 2:
        shape = tuple(edge_index.shape) if isinstance(edge_index, Tensor) else type(edge_index).__name__
        raise ValueError(f"edge_index must be a (2, E) tensor, got {shape}")
    if edge_index.dtype != torch.long:
        raise ValueError(f"edge_index must have dtype torch.long, got {edge_index.dtype}")


def _check_finite(inputs: Sequence[tuple[str, Any]]) -> None:
    """Raise a ``ValueError`` naming the first floating-point tensor among ``(name, value)`` pairs that holds
    NaN or inf. One device synchronization for all of them (a second one only to describe a failure)."""
    tensors = [(n, t) for n, t in inputs if isinstance(t, Tensor) and t.is_floating_point()]
    if not tensors:
        return
    flags = [torch.isfinite(t).all() for _, t in tensors]
    ok = torch.stack(flags) if len({f.device for f in flags}) == 1 else torch.tensor([bool(f) for f in flags])
    if bool(ok.all()):
        return
    name, t = tensors[int((~ok).nonzero()[0, 0])]
    bad = ~torch.isfinite(t)
    raise ValueError(
        f"{name} contains NaN or inf ({int(bad.sum())} of {t.numel()} entries, the first at index "
        f"{tuple(bad.nonzero()[0].tolist())})"
    )


def _check_layer_dtypes(layer: nn.Module, inputs: Sequence[tuple[str, Any]], err: Exception) -> None:
    """After ``layer`` raised ``err``: raise a ``TypeError`` naming the first floating-point input whose dtype
    differs from the layer's parameters (torch reports that as a bare ``RuntimeError`` from a matmul)."""
    dtypes = {p.dtype for p in layer.parameters() if p.dtype.is_floating_point}
    if len(dtypes) != 1:
        return
    (want,) = dtypes
    for name, t in inputs:
        if isinstance(t, Tensor) and t.is_floating_point() and t.dtype != want:
            raise TypeError(
                f"{name} has dtype {t.dtype}, but the parameters of {type(layer).__name__} have dtype "
                f"{want}: cast the inputs (.to({want})) or the layer (.to({t.dtype})); the layer failed with: {err}"
            ) from err


def _check_same_dtype(what: str, t: Tensor, x: Tensor) -> None:
    if t.dtype != x.dtype and t.is_floating_point() and x.is_floating_point():
        raise TypeError(f"{what} has dtype {t.dtype} but x has {x.dtype}: cast it with .to(x.dtype)")


def _check_pos(spec: _Spec, pos, x: Tensor) -> None:
    """``pos``: ``(N, d)`` or a ``(source, target)`` pair, of the position type's width and the dtype of ``x``."""
    p_src, p_dst, bipartite = _as_pair(pos, "pos")
    pt = spec.pos_field(p_dst)
    for name, p in (("pos (source)", p_src), ("pos (target)", p_dst)) if bipartite else (("pos", p_dst),):
        _check_rows(pt, p, name)
        _check_same_dtype(name, p, x)


def _check_edge_attr(spec: _Spec, edge_attr, num_edges: int, x: Tensor) -> None:
    """``edge_attr``: ``(E, edge_type.dim)`` in the dtype of ``x`` if typed; ``(E,)`` or ``(E, k)`` if invariant."""
    if not isinstance(edge_attr, Tensor):
        raise TypeError(f"edge_attr must be a torch.Tensor, got {type(edge_attr).__name__}")
    et = spec.edge_type
    if et is not None:
        _check_rows(et, edge_attr, "edge_attr", rows="E")
        _check_same_dtype("edge_attr", edge_attr, x)
    elif edge_attr.dim() not in (1, 2):
        raise ValueError(
            f"edge_attr has shape {tuple(edge_attr.shape)}, expected (E,) or (E, edge_dim): one row per edge "
            "and no batch dimension"
        )
    if edge_attr.shape[0] != num_edges:
        raise ValueError(f"edge_attr has {edge_attr.shape[0]} rows, edge_index has {num_edges} edges")
