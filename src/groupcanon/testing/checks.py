"""Assertions for group axioms, action laws and equivariance of functions.

Tolerances: by default ``1e-10`` (scaled by the magnitude of the numbers compared) in float64 and ``1e-4`` in
float32; pass ``atol`` to override. Every check raises ``AssertionError`` naming the law, the worst error and the
tolerance, and returns the worst error when it passes.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from ..features import FeatureType
from ..field_type import FieldType
from ..group import Group, require_group

__all__ = [
    "assert_equivariant",
    "assert_invariant",
    "check_action_laws",
    "check_group_axioms",
    "default_atol",
    "equivariance_error",
]

_DEFAULT_ATOL = {torch.float64: 1e-10, torch.float32: 1e-4, torch.float16: 1e-2, torch.bfloat16: 5e-2}


def default_atol(dtype: torch.dtype) -> float:
    """The kit's default absolute tolerance for ``dtype`` (float64 1e-10, float32 1e-4)."""
    return _DEFAULT_ATOL.get(dtype, 1e-4)


def _err(a: Tensor, b: Tensor) -> float:
    if a.shape != b.shape:
        a, b = torch.broadcast_tensors(a, b)
    if a.numel() == 0:
        return 0.0
    return float((a - b).detach().abs().max())


def _scale(*ts: Tensor) -> float:
    m = max((float(t.detach().abs().max()) for t in ts if t.numel()), default=1.0)
    return max(1.0, m)


def _fail(law: str, err: float, tol: float, detail: str = "") -> None:
    raise AssertionError(f"{law}: max error {err:.3e} > tolerance {tol:.1e}" + (f" ({detail})" if detail else ""))


def _samples(group: Group, n: int, dtype, device, generator) -> Tensor:
    """``n`` elements: random ones, the first up to ``n // 2`` of them replaced by the group's special
    (near-singular) elements, placed last so that a small ``n`` still tests random elements first."""
    special = group.special_elements(dtype=dtype, device=device)
    rand = group.sample(n, generator=generator, dtype=dtype, device=device)
    k = min(n // 2, special.shape[0])
    return torch.cat((rand[: n - k], special[:k])) if k else rand


def check_group_axioms(
    group: Group,
    *,
    n: int = 32,
    dtype: torch.dtype = torch.float64,
    device=None,
    atol: float | None = None,
    generator: torch.Generator | None = None,
    elements: tuple[Tensor, Tensor, Tensor] | None = None,
) -> float:
    """Check identity, inverse, associativity, broadcasting, and (where implemented) ``matrix`` as a
    homomorphism, ``exp``/``log`` round trips and the affine interface, on ``n`` sampled triples.

    ``elements`` may supply the triple ``(a, b, c)`` (each ``(n, *element_shape)``), e.g. from
    :func:`groupcanon.testing.strategies.elements`.
    """
    require_group(group, "check_group_axioms() argument group")
    tol = default_atol(dtype) if atol is None else atol
    if elements is None:
        gen = generator or torch.Generator(device=device or "cpu").manual_seed(0)
        a = _samples(group, n, dtype, device, gen)
        b = group.sample(n, generator=gen, dtype=dtype, device=device)
        c = group.sample(n, generator=gen, dtype=dtype, device=device)
    else:
        a, b, c = elements
    for name, t in (("a", a), ("b", b), ("c", c)):
        group.check(t, f"sample {name}")
    shape = tuple(group.element_shape)
    e = group.identity(*group.batch_shape(a), dtype=a.dtype, device=a.device)
    if tuple(e.shape) != (*group.batch_shape(a), *shape):
        _fail("identity shape", float("inf"), tol, f"got {tuple(e.shape)}")
    s = tol * _scale(a, b, c)
    worst = 0.0
    laws = {
        "left identity e.a = a": (group.compose(e, a), a),
        "right identity a.e = a": (group.compose(a, e), a),
        "right inverse a.a^-1 = e": (group.compose(a, group.inverse(a)), e),
        "left inverse a^-1.a = e": (group.compose(group.inverse(a), a), e),
        "involution (a^-1)^-1 = a": (group.inverse(group.inverse(a)), a),
        "associativity (a.b).c = a.(b.c)": (
            group.compose(group.compose(a, b), c),
            group.compose(a, group.compose(b, c)),
        ),
    }
    for law, (lhs, rhs) in laws.items():
        err = _err(lhs, rhs)
        worst = max(worst, err)
        if not err <= s:
            _fail(f"{group}: {law}", err, s)
    # broadcasting: (n, 1) . (1, n) -> (n, n)
    ab = group.compose(a.unsqueeze(1), b.unsqueeze(0))  # batch dims lead, so this is (n, 1) . (1, n)
    nb = a.shape[0]
    if tuple(ab.shape) != (nb, nb, *shape):
        _fail(f"{group}: compose broadcasting", float("inf"), s, f"got shape {tuple(ab.shape)}")
    idx = torch.arange(nb, device=a.device)
    err = _err(ab[idx, idx], group.compose(a, b))
    if not err <= s:
        _fail(f"{group}: compose broadcasting (n,1).(1,n) diagonal = a.b", err, s)
    try:
        ma, mb, mab = group.matrix(a), group.matrix(b), group.matrix(group.compose(a, b))
    except NotImplementedError:
        pass
    else:
        err = _err(mab, ma @ mb)
        worst = max(worst, err)
        if not err <= s * _scale(ma, mb):
            _fail(f"{group}: matrix(a.b) = matrix(a) matrix(b)", err, s)
    try:
        back = group.exp(group.log(a))
    except NotImplementedError:
        pass
    else:
        err = _err(back, a)
        worst = max(worst, err)
        if not err <= 10 * s:
            _fail(f"{group}: exp(log(a)) = a", err, 10 * s)
    if group.space_dim is not None:
        gen = torch.Generator(device=device or "cpu").manual_seed(1)
        p = torch.randn(a.shape[0], group.space_dim, generator=gen, dtype=a.dtype, device=a.device)
        lhs = group.transform(group.compose(a, b), p)
        rhs = group.transform(a, group.transform(b, p))
        err = _err(lhs, rhs)
        worst = max(worst, err)
        if not err <= s * _scale(p):
            _fail(f"{group}: transform(a.b, p) = transform(a, transform(b, p))", err, s)
        try:
            rot = group.rotation(a)
        except NotImplementedError:
            rot = None
        if rot is not None:
            err = _err((rot @ p.unsqueeze(-1)).squeeze(-1), group.rotate(a, p))
            if not err <= s * _scale(p):
                _fail(f"{group}: rotate(a, v) = rotation(a) v", err, s)
            eye = torch.eye(group.space_dim, dtype=a.dtype, device=a.device)
            err = _err(rot @ rot.transpose(-1, -2), eye)
            if not err <= s:
                _fail(f"{group}: rotation(a) is orthonormal", err, s)
            if group.orientation_preserving and not bool((torch.linalg.det(rot) > 0).all()):
                _fail(f"{group}: det rotation(a) = +1 (orientation_preserving)", float("inf"), s)
        worst = max(worst, _affine_consistency(group, a, p, s))
    return worst


def _affine_consistency(group: Group, a: Tensor, p: Tensor, s: float) -> float:
    """Vectors and points move together: ``rotate(a, p) = transform(a, p) - transform(a, 0)``, ``translation(a) =
    transform(a, 0)``, and ``matrix(a)`` moves them as ``rotate`` (a linear ``(d, d)`` one) or ``transform`` (a
    homogeneous ``(d + 1, d + 1)`` one) does."""
    worst = 0.0
    zero = torch.zeros_like(p)
    origin = group.transform(a, zero)
    checks = [("rotate(a, v) = transform(a, v) - transform(a, 0)", group.rotate(a, p), group.transform(a, p) - origin)]
    try:
        checks.append(("translation(a) = transform(a, 0)", group.translation(a), origin))
    except NotImplementedError:
        pass
    d = group.space_dim
    try:
        m = group.matrix(a)
    except NotImplementedError:
        m = None
    if m is not None and tuple(m.shape[-2:]) == (d, d):
        checks.append(("matrix(a) v = rotate(a, v)", (m @ p.unsqueeze(-1)).squeeze(-1), group.rotate(a, p)))
    if m is not None and tuple(m.shape[-2:]) == (d + 1, d + 1):
        ph = torch.cat((p, torch.ones_like(p[..., :1])), dim=-1)
        moved = (m @ ph.unsqueeze(-1)).squeeze(-1)
        checks.append(
            ("matrix(a) [p; 1] = [transform(a, p); 1]", moved, torch.cat((group.transform(a, p), ph[..., -1:]), dim=-1))
        )
    for law, lhs, rhs in checks:
        err = _err(lhs, rhs)
        worst = max(worst, err)
        if not err <= s * _scale(p, origin):
            _fail(f"{group}: {law}", err, s * _scale(p, origin))
    return worst


def _bind(group: Group, ft: FeatureType | FieldType) -> FieldType:
    if not isinstance(ft, (FeatureType, FieldType)):
        raise TypeError(
            f"check_action_laws() argument feature_type must be a FeatureType or FieldType, got {type(ft).__name__}"
        )
    if isinstance(ft, FieldType):
        if ft.group != group:
            raise ValueError(f"FieldType is over {ft.group}, not {group}")
        return ft
    return FieldType(group, [ft])


def check_action_laws(
    group: Group,
    feature_type: FeatureType | FieldType,
    *,
    n: int = 32,
    dtype: torch.dtype = torch.float64,
    device=None,
    atol: float | None = None,
    generator: torch.Generator | None = None,
    elements: tuple[Tensor, Tensor] | None = None,
    x: Tensor | None = None,
) -> float:
    """Check that ``feature_type.act`` is a group action: ``act(e, x) = x``, ``act(a, act(b, x)) = act(a.b, x)``,
    ``act(a^-1, act(a, x)) = x``, and that it keeps shape, dtype and broadcasts a single element over a batch.
    """
    require_group(group, "check_action_laws() argument group")
    tol = default_atol(dtype) if atol is None else atol
    ft = _bind(group, feature_type)
    gen = generator or torch.Generator(device=device or "cpu").manual_seed(0)
    if elements is None:
        a = _samples(group, n, dtype, device, gen)
        b = group.sample(n, generator=gen, dtype=dtype, device=device)
    else:
        a, b = elements
    nb = a.shape[0]
    if x is None:
        x = torch.randn(nb, ft.dim, generator=gen, dtype=a.dtype, device=a.device)
    e = group.identity(nb, dtype=a.dtype, device=a.device)
    s = tol * _scale(x, a, b)
    worst = 0.0
    ax = ft.act(a, x)
    if ax.shape != x.shape or ax.dtype != x.dtype or ax.device != x.device:
        _fail(f"{ft!r}: act keeps shape/dtype/device", float("inf"), s, f"{tuple(x.shape)} -> {tuple(ax.shape)}")
    laws = {
        "identity act(e, x) = x": (ft.act(e, x), x),
        "compatibility act(a, act(b, x)) = act(a.b, x)": (
            ft.act(a, ft.act(b, x)),
            ft.act(group.compose(a, b), x),
        ),
        "inverse act(a^-1, act(a, x)) = x": (ft.act(group.inverse(a), ax), x),
        # the first element: a random one (the special ones, the identity among them, come last)
        "broadcast act(a_k, x) = act(a_k repeated, x)": (
            ft.act(a[0], x),
            ft.act(a[:1].expand(nb, *a.shape[1:]), x),
        ),
    }
    for law, (lhs, rhs) in laws.items():
        err = _err(lhs, rhs)
        worst = max(worst, err)
        if not err <= s:
            _fail(f"{ft!r}: {law}", err, s)
    return worst


# ----------------------------------------------------------------------------------------- equivariance
TypeSpec = FieldType | FeatureType | Group | None


def _transform(group: Group, spec: TypeSpec, value: Any, g: Tensor) -> Any:
    if spec is None:
        return value
    if isinstance(value, (tuple, list)):
        return type(value)(_transform(group, spec, v, g) for v in value)
    if isinstance(spec, Group):
        return group.compose(g, value)  # frames transform by left multiplication
    if isinstance(spec, FeatureType):
        spec = FieldType(group, [spec])
    return spec.act(g, value)


def _check_type_specs(what: str, specs: Any) -> None:
    """Raise a ``TypeError`` naming the entry of ``in_types`` / ``out_types`` that is not a :data:`TypeSpec`."""
    if what == "in_types" and not isinstance(specs, Mapping):
        raise TypeError(
            f"in_types must be a mapping (argument position or keyword -> type), got {type(specs).__name__}"
        )
    if isinstance(specs, Mapping):
        items = specs.items()
    elif isinstance(specs, (tuple, list)):
        items = enumerate(specs)
    else:
        items = [(None, specs)]
    for key, spec in items:
        if spec is not None and not isinstance(spec, (FieldType, FeatureType, Group)):
            where = what if key is None else f"{what}[{key!r}]"
            raise TypeError(f"{where} must be a FieldType, FeatureType, Group or None, got {type(spec).__name__}")


def _outputs(out: Any) -> tuple:
    return tuple(out) if isinstance(out, (tuple, list)) else (out,)


def equivariance_error(
    fn: Callable,
    group: Group,
    args: Sequence = (),
    kwargs: Mapping | None = None,
    *,
    in_types: Mapping[int | str, TypeSpec],
    out_types: TypeSpec | Sequence[TypeSpec] = None,
    g: Tensor | None = None,
    n_samples: int = 4,
    generator: torch.Generator | None = None,
) -> float:
    """Worst ``|fn(g . inputs) - g . fn(inputs)|`` over ``n_samples`` global elements ``g`` (or the given ``g``).

    Args:
        fn: the function under test, called as ``fn(*args, **kwargs)``.
        in_types: how each input transforms, keyed by position (int) or keyword (str): a FieldType or FeatureType
            (``act``), a Group (the value holds frames, which transform as ``g . frames``), or None (unchanged).
            Inputs not listed are passed unchanged (edge indices, masks, invariant attributes).
        out_types: the same for the outputs (a sequence for tuple outputs). ``None``: invariant output.
        g: one element ``(*element_shape)`` or a batch ``(k, *element_shape)`` of global transforms to test.
    """
    require_group(group, "equivariance_error() argument group")
    if not callable(fn):
        raise TypeError(f"equivariance_error() argument fn must be callable, got {type(fn).__name__}")
    _check_type_specs("in_types", in_types)
    _check_type_specs("out_types", out_types)
    kwargs = dict(kwargs or {})
    args = list(args)
    if g is None:
        # the first floating-point input sets dtype and device (not an edge_index that happens to come first)
        floats = (v for v in list(args) + list(kwargs.values()) if isinstance(v, Tensor) and v.is_floating_point())
        ref = next(floats, None)
        dtype = ref.dtype if ref is not None else torch.get_default_dtype()
        device = ref.device if ref is not None else None
        gen = generator or torch.Generator(device=device or "cpu").manual_seed(0)
        g = _samples(group, n_samples, dtype, device, gen)
    group.check(g, "g")
    gs = g.reshape(-1, *group.element_shape) if g.dim() > len(group.element_shape) else g.unsqueeze(0)
    for key in in_types:
        if isinstance(key, int) and not 0 <= key < len(args):
            raise ValueError(f"in_types refers to positional argument {key}, but only {len(args)} were given")
        if isinstance(key, str) and key not in kwargs:
            raise ValueError(f"in_types refers to keyword {key!r}, which was not given")
    outs = _outputs(fn(*args, **kwargs))
    o_types = tuple(out_types) if isinstance(out_types, (tuple, list)) else (out_types,) * len(outs)
    if len(o_types) != len(outs):
        raise ValueError(f"fn returned {len(outs)} outputs but out_types has {len(o_types)} entries")
    worst = 0.0
    for gi in gs:
        t_args = [_transform(group, in_types.get(i), a, gi) for i, a in enumerate(args)]
        t_kwargs = {k: _transform(group, in_types.get(k), v, gi) for k, v in kwargs.items()}
        t_outs = _outputs(fn(*t_args, **t_kwargs))
        for o, to, ot in zip(outs, t_outs, o_types):
            if o is None or not isinstance(o, Tensor):
                continue
            expected = _transform(group, ot, o, gi)
            worst = max(worst, _err(to, expected))
    return worst


def assert_equivariant(
    fn: Callable,
    group: Group,
    args: Sequence = (),
    kwargs: Mapping | None = None,
    *,
    in_types: Mapping[int | str, TypeSpec],
    out_types: TypeSpec | Sequence[TypeSpec] = None,
    g: Tensor | None = None,
    n_samples: int = 4,
    atol: float | None = None,
    rtol: float = 0.0,
    generator: torch.Generator | None = None,
) -> float:
    """Assert ``fn(g . inputs) == g . fn(inputs)`` within ``atol + rtol * max|output|``; return the worst error.

    See :func:`equivariance_error` for the arguments. ``atol`` defaults to :func:`default_atol` of the outputs'
    dtype (an absolute tolerance: pass ``rtol`` to scale with the outputs' magnitude).
    """
    err = equivariance_error(
        fn,
        group,
        args,
        kwargs,
        in_types=in_types,
        out_types=out_types,
        g=g,
        n_samples=n_samples,
        generator=generator,
    )
    outs = [o for o in _outputs(fn(*args, **(kwargs or {}))) if isinstance(o, Tensor)]
    dtype = outs[0].dtype if outs else torch.get_default_dtype()
    scale = _scale(*outs) if outs else 1.0
    tol = (default_atol(dtype) if atol is None else atol) + rtol * scale
    if not err <= tol:
        kind = "invariant" if out_types is None else "equivariant"
        _fail(f"{getattr(fn, '__name__', type(fn).__name__)} is not {kind} under {group}", err, tol)
    return err


def assert_invariant(fn: Callable, group: Group, args: Sequence = (), kwargs: Mapping | None = None, **options):
    """Assert ``fn(g . inputs) == fn(inputs)``: :func:`assert_equivariant` with invariant outputs."""
    options.pop("out_types", None)
    return assert_equivariant(fn, group, args, kwargs, out_types=None, **options)
