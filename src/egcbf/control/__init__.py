"""The robot-independent control machinery: the QP cores every hand-crafted CBF-QP is solved with
(:mod:`~egcbf.control.qp` sparse, :mod:`~egcbf.control.dense_qp` and :mod:`~egcbf.control.dense_ipm` batched dense,
:mod:`~egcbf.control.ipm` the interior-point core, :mod:`~egcbf.control.sparse_solvers` the qpsolvers back-ends), the
constraint rows they read (:mod:`~egcbf.control.constraints`), the acceleration-level barriers of every control-affine
point-mass robot (:mod:`~egcbf.control.point_mass_qp`), and the registry of hand-crafted controllers
(:mod:`~egcbf.control.controllers`, ``make_controller``).

A robot's own controllers (its nominal controller, inner loop and hand-crafted barriers) live with the robot in
:mod:`egcbf.robots` (the quadrotor's in :mod:`egcbf.robots.quadrotor`).
"""
