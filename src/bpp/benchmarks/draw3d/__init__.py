"""DrawAnything-Real: the paper's real drawing benchmark, on a simulated 6-DoF arm."""
