"""Reference solutions of the centralized CBF-QP from the hand-written solver adapters that egcbf had before it
solved through qpsolvers, for the regression test in test_cbf_qp.py (``tests/egcbf/data/qp_reference.json``).

Each entry is a scene (``numpy_rows(seed, n)`` of test_cbf_qp.py), the optimum each solver returned at
``eps_abs = 1e-9`` and the same after ``polish_sparse`` (the exact optimum to rounding). Recorded once, by the code
of commit e5a0b87 (the adapters), with

    python tests/egcbf/qp_reference.py

and never regenerated to make a change pass.
"""

from __future__ import annotations

import json
from pathlib import Path

DATA = Path(__file__).resolve().parent / "data" / "qp_reference.json"
SCENES = ((6, 30), (11, 60), (21, 120))
LEGACY_SOLVERS = ("piqp", "proxsuite", "osqp", "clarabel")


def main() -> None:
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_cbf_qp import numpy_rows

    from egcbf.qp.sparse_qp import assemble_centralized, polish_sparse, solve_sparse

    out = []
    for seed, n in SCENES:
        prep, cons = numpy_rows(seed, n=n)
        qp = assemble_centralized(prep.a_nom[0], cons, prep.bC[0], prep.blo[0], prep.bhi[0])
        entry = {"seed": seed, "n": n, "solutions": {}, "polished": {}}
        for s in LEGACY_SOLVERS:
            res = solve_sparse(qp, s, eps_abs=1e-9)
            assert res.ok, (s, res.status)
            entry["solutions"][s] = res.x.tolist()
            entry["polished"][s] = polish_sparse(qp, res.x)[0].tolist()
        out.append(entry)
    DATA.write_text(json.dumps(out) + "\n")
    print(f"wrote {DATA}")


if __name__ == "__main__":
    main()
