"""The studio: prompt a trained policy yourself (``bpp studio``).

A local web page where a person draws a prompt on the DrawAnything board (mouse, pen or touch, sampled at the env's
10 Hz), picks a stored demonstration or uploads a drawing file, and watches one or two policies redraw it live at a
new board angle, with the Chamfer score and the prompt attention as they go; plus the HTTP API the page uses, open to
other clients (a phone, another workstation, a script: :mod:`bpp.benchmarks.draw.studio.client`).
"""
