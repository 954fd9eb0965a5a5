"""Drawings and how they are scored, shared by the drawing benchmarks (DrawAnything-Sim, :mod:`bpp.benchmarks.draw`,
and DrawAnything-Real on a simulated arm, :mod:`bpp.benchmarks.draw3d`): the drawing task (:mod:`~bpp.drawing.drawing`),
where drawings come from (generated, :mod:`~bpp.drawing.procedural`; human-made, :mod:`~bpp.drawing.human`; files,
:mod:`~bpp.drawing.files`), the canvas and board frames (:mod:`~bpp.drawing.geometry`), the canvas's pixels
(:mod:`~bpp.drawing.raster`), the Chamfer metric (:mod:`~bpp.drawing.metric`), and the physical canvas with
red corner markers whose pose a photo gives (:mod:`~bpp.drawing.marked_canvas`: DrawAnything-Real's, measured by
the arm's scene camera or by an iPhUMI phone's)."""
