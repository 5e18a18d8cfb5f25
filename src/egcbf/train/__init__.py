"""Training: the loop (:mod:`~egcbf.train.loop`), checkpoints, their configs and loading
(:mod:`~egcbf.train.checkpoint`), and weight averaging between checkpoints (:mod:`~egcbf.train.averaging`)."""
