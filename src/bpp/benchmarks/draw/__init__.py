"""DrawAnything-Sim: draw an unseen drawing on a rotated board from one demonstration of it."""
