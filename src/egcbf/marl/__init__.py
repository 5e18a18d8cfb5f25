"""Safe multi-agent RL baselines trained through the TorchRL environment (:mod:`egcbf.env.torchrl`).

* :mod:`.networks`: the per-agent actor and critic over the observation layout of :mod:`egcbf.env.observations`
  (shared parameters, permutation-invariant pooling of neighbours and LiDAR hits); plain torch;
* :mod:`.checkpoint`: their checkpoints (``model.safetensors`` + ``marl.json``), read without TorchRL;
* :mod:`.controller`: a trained actor as a swarm controller (``u, info = controller(state, env_config)``), what
  ``egcbf eval`` runs;
* :mod:`.ppo_lagrangian`: IPPO with a Lagrangian cost constraint, built from TorchRL's collector, GAE and clipped
  PPO loss (the optional ``marl`` extra).
"""

__all__ = ["MARL_METHODS"]

#: the MARL baselines' method names (a checkpoint's ``MarlTrainConfig.algo``)
MARL_METHODS = ("ippo-lag",)
