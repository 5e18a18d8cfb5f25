"""The QP cores every hand-crafted CBF-QP and run-time filter is solved with: the constraint rows
(:mod:`~egcbf.qp.constraints`), the centralized sparse QP (:mod:`~egcbf.qp.sparse_qp`) and its qpsolvers back-ends
(:mod:`~egcbf.qp.sparse_solvers`), the batched dense per-agent QPs (:mod:`~egcbf.qp.dense_qp`,
:mod:`~egcbf.qp.dense_ipm`) and the interior-point core (:mod:`~egcbf.qp.ipm`). Robot-independent: a robot's
barriers (:mod:`egcbf.robots`) fill the rows."""
