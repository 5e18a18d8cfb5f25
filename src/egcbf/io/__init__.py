"""Files and the machine: atomic writes and directory swaps (:mod:`~egcbf.io.atomic`), directory locks
(:mod:`~egcbf.io.locks`), markdown reports with regenerated blocks and provenance records (:mod:`~egcbf.io.report`),
torch's thread count (:mod:`~egcbf.io.threads`) and the allocator and memory limits (:mod:`~egcbf.io.allocator`).
Nothing here knows a robot, a network or a controller."""
