"""The paper's quadrotor, as one robot package (the pattern every robot follows, docs/robots.md):

* :mod:`~egcbf.robots.quadrotor.dynamics`: the rigid body (state layout, control-affine vector field, the
  SO(3)-preserving integrator, its parameters and the symmetry's action), with :mod:`~egcbf.robots.quadrotor.so3`
  (the SO(3) maps it integrates with) and :mod:`~egcbf.robots.quadrotor.calibrate` (the measurements behind its
  step defaults, ``python -m egcbf.robots.quadrotor.calibrate``);
* :mod:`~egcbf.robots.quadrotor.nominal`: its equivariant geometric controller, and the inner loop
  (:func:`~egcbf.robots.quadrotor.nominal.track_acceleration`) that turns an acceleration command into body torque
  and thrust;
* :mod:`~egcbf.robots.quadrotor.barriers`: its hand-crafted barriers (through the thrust-vector double-integrator
  model); :mod:`~egcbf.robots.quadrotor.cbf_qp` (the two loops around the filter, the shared configuration, the
  cCBF-QP) and :mod:`~egcbf.robots.quadrotor.dcbf_qp` (the dCBF-QP) built on them, on the generic QP cores of
  :mod:`egcbf.control`;
* :mod:`~egcbf.robots.quadrotor.robot`: :class:`Quadrotor`, the :class:`~egcbf.robots.base.Robot` the swarm, the
  graph and the learner read.

Only :class:`Quadrotor` is imported here; import the modules by name.
"""

from .robot import Quadrotor

__all__ = ["Quadrotor"]
