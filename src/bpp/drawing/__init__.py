"""Drawings and how they are scored, shared by the drawing benchmarks (DrawAnything-Sim, :mod:`bpp.benchmarks.draw`,
and DrawAnything-Real on a simulated arm, :mod:`bpp.benchmarks.draw3d`): the drawing task (:mod:`~bpp.drawing.drawing`),
where drawings come from (generated, :mod:`~bpp.drawing.procedural`; human-made, :mod:`~bpp.drawing.human`; files,
:mod:`~bpp.drawing.files`), the canvas and board frames (:mod:`~bpp.drawing.geometry`), the canvas's pixels
(:mod:`~bpp.drawing.raster`) and the Chamfer metric (:mod:`~bpp.drawing.metric`)."""
