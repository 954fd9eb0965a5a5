"""LeRobot datasets as a benchmark without a simulator: ``bpp lerobot import`` turns a LeRobot v3 dataset into an
episode store, ``bpp lerobot export`` turns any store into a LeRobot v3 dataset, and evaluation replays held-out
episodes open loop and scores the action error."""
