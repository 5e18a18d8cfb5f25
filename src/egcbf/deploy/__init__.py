"""Deployment: one agent's controller from its own observations (:mod:`~egcbf.deploy.agent`) and its export to
ONNX and TorchScript with a parity check (:mod:`~egcbf.deploy.export`)."""
