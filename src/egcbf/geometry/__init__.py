"""Pure geometry, no robot and no swarm: neighbour search within a radius (:mod:`~egcbf.geometry.neighbors`,
sparse ``(2, E)`` edge lists, never dense ``N x N``) and axis-aligned boxes, their distances and ray hits
(:mod:`~egcbf.geometry.rectangles`)."""
