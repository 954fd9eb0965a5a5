"""bpp: Behavior Prompting Policy — demonstrations as prompts for manipulation."""

__version__ = "0.1.0"
