"""Controllers as plug-ins: the registry of hand-crafted controllers (:mod:`~egcbf.control.controllers`), the one
place that builds any controller from a name ``METHOD[:FILTER]`` and a checkpoint (:mod:`~egcbf.control.resolve`),
the run-time safety filters as registered classes (:mod:`~egcbf.control.filters`) and the controller and filter
names (:mod:`~egcbf.control.names`).

A robot's own controllers (its nominal law, inner loop and hand-crafted barriers and CBF-QPs) live with the robot in
:mod:`egcbf.robots`, which declares them; the QP cores are :mod:`egcbf.qp`.
"""
