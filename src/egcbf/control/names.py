"""The names of the run-time safety filters and of a controller behind one, ``METHOD:FILTER``.

``egcbf eval --checkpoint checkpoints/egcbf+ --filter dcbf`` records its controller as ``egcbf+:dcbf``; ``egcbf demo
--compare`` and ``egcbf reproduce --methods`` take the same names. This module (no dependency: the command line
and the reproduction import it without torch) is the one place that parses and writes them:

    split_method("egcbf+:dcbf") == ("egcbf+", "dcbf")
    split_method("egcbf+") == ("egcbf+", "none")
    join_method("egcbf+", "dcbf") == "egcbf+:dcbf"
    path_name("egcbf+:dcbf") == "egcbf+_dcbf"      # a folder or file name (no colon in paths)

The filters themselves are :mod:`egcbf.control.filters` (docs/safety_filters.md).
"""

from __future__ import annotations

__all__ = ["FILTERS", "FILTER_LABELS", "filter_label", "join_method", "path_name", "split_method"]

#: the run-time filters of ``egcbf eval --filter`` (``"none"``: the policy alone); :mod:`egcbf.control.filters`
FILTERS = ("none", "cbf", "prior", "dcbf")
#: what each filter is, in a label: ``"EGCBF+ + dCBF filter"``
FILTER_LABELS = {"dcbf": "dCBF filter", "cbf": "learned-CBF filter", "prior": "prior-CBF filter"}


def split_method(name: str) -> tuple[str, str]:
    """``(method, filter)`` of a controller name: ``"egcbf+:dcbf"`` -> ``("egcbf+", "dcbf")``, ``"egcbf+"`` ->
    ``("egcbf+", "none")``. Raises ``ValueError`` naming the valid filters for an empty method or filter, more than
    one ``:``, or a filter outside :data:`FILTERS` (whether ``method`` exists is the caller's to check)."""
    method, colon, filt = name.partition(":")
    if not colon:
        filt = "none"
    if not method or ":" in filt or filt not in FILTERS:
        raise ValueError(
            f"bad controller name {name!r}: write METHOD or METHOD:FILTER with FILTER one of {list(FILTERS[1:])} "
            "(e.g. egcbf+:dcbf)"
        )
    return method, filt


def join_method(method: str, filt: str = "none") -> str:
    """The name of ``method`` behind the filter ``filt``: ``"egcbf+:dcbf"``, or ``method`` itself for ``"none"``
    (the inverse of :func:`split_method`)."""
    if not method or ":" in method or filt not in FILTERS:
        raise ValueError(f"join_method needs a method without ':' and a filter of {list(FILTERS)}, got {method!r}, "
                         f"{filt!r}")  # fmt: skip
    return method if filt == "none" else f"{method}:{filt}"


def path_name(name: str) -> str:
    """``name`` as a folder or file name: ``METHOD:FILTER`` as ``METHOD_FILTER`` (no colon in paths)."""
    return name.replace(":", "_")


def filter_label(label: str, filt: str) -> str:
    """The label of a controller labelled ``label`` behind ``filt``: ``"EGCBF+ + dCBF filter"``; ``label`` itself
    for ``"none"``."""
    return label if filt == "none" else f"{label} + {FILTER_LABELS.get(filt, filt + ' filter')}"
