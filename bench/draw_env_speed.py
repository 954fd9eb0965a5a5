"""DrawAnything-Sim env speed on one core: steps/s without images and with images at several resolutions.

Actions replay scripted demonstrations of the unseen human-made drawings (realistic pen-down ink), so the
renderer does the same work as during evaluation. With ``--metric``, also with the Chamfer metric against a realistic
target (the demonstration's own ink, upright, which is what evaluation scores against), computed every step (the
env's default) or only at the episode's end, the best score of every step included (evaluation's setting).

    python bench/draw_env_speed.py [--steps 20000] [--metric]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bpp.benchmarks.draw.demonstrator import demonstrate, replay_paths
from bpp.benchmarks.draw.env import DrawEnv
from bpp.drawing.geometry import canvas_to_upright
from bpp.drawing.human import human_drawings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=20000, help="env steps per setting")
    parser.add_argument("--metric", action="store_true", help="also time with a target set")
    args = parser.parse_args()
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})  # one core, as the target is per core
    rng = np.random.default_rng(0)
    demos = [demonstrate(d, rng.uniform(-0.7, 0.7), rng.uniform(50, 450, 2), rng) for d in human_drawings()[:20]]
    targets = [[canvas_to_upright(p, d.board_angle) for p in replay_paths(d.states, d.actions)] for d in demos]
    settings = [("no image", None, None)] + [(f"{s}x{s} image", s, None) for s in (64, 96, 224)]
    if args.metric:
        settings += [
            ("no image + metric", None, True),
            ("96x96 image + metric", 96, True),
            ("no image + metric at end", None, False),
            ("96x96 image + metric at end", 96, False),
        ]
    print(f"{'setting':28s} {'steps/s':>10s}")
    for name, size, every_step in settings:
        env = DrawEnv(image_size=size, early_stop=False, score_every_step=every_step is not False)
        steps, k = 0, 0
        t0 = time.perf_counter()
        while steps < args.steps:
            demo, target = demos[k % len(demos)], targets[k % len(demos)]
            k += 1
            options = {"board_angle": demo.board_angle, "cursor": demo.states[0, :2]}
            if every_step is not None:
                options["target"] = target
            env.max_episode_steps = len(demo.actions)  # the last action ends the episode (and scores it)
            env.reset(options=options)
            for action in demo.actions:
                env.step(action)
            steps += len(demo.actions)
        rate = steps / (time.perf_counter() - t0)
        print(f"{name:28s} {rate:10.0f}")


if __name__ == "__main__":
    main()
