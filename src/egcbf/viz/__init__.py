"""Pictures: episode renders and GIFs (:mod:`~egcbf.viz.render`), CBF contour plots (:mod:`~egcbf.viz.contour`),
training curves (:mod:`~egcbf.viz.curves`)."""
