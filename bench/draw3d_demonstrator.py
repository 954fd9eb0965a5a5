"""DrawAnything-Real's scripted demonstrator on the simulated arm: how well its ink matches the drawing, how often a
demonstration fails, and how fast the simulation runs.

For each of N procedural drawings (DrawAnything's training distribution), the canvas is placed at random on the
board (±45 degrees); its pose is measured from the scene camera's photo (the arm swung aside), as a lab would; the
demonstrator plans in that measured frame and the arm executes the plan. The ink is scored against the drawing with
DrawAnything's Chamfer metric (pixels of its 512-px canvas; the drawing's unit square is its 350-px board). A
demonstration fails when the photo gives no pose (a marker hidden or unclear) or its Chamfer is over the threshold.

Each kept demonstration is also scored as a lab would, from a scene-camera photo of the board rectified through the
markers (:func:`bpp.benchmarks.draw3d.photo.photograph_canvas`), against its own drawing and against the next drawing
(a wrong one, for scores in the tens of pixels); the table gives how far the photo's score is from the exact one.

Speed is given against MuJoCo's physics alone (its ``mj_step`` calls, timed in the same run): the rest of a control
step is the operational-space controller, the ink and the recording, in Python.

    python bench/draw3d_demonstrator.py [--n 40] [--seed 0] [--threshold 3.0]
"""

from __future__ import annotations

import argparse
import time
import types
from collections import Counter

import numpy as np

from bpp.benchmarks.draw3d.dataset import ASIDE
from bpp.benchmarks.draw3d.demonstrator import ScriptConfig, execute, ink_chamfer, pixels_to_mm, plan_drawing
from bpp.benchmarks.draw3d.photo import photograph_canvas, rectified_chamfer
from bpp.benchmarks.draw3d.scene import BOARD, CONTROL_HZ, HOME_QPOS, Scene, canvas_transform
from bpp.drawing.marked_canvas import CanvasNotFound, canvas_in_base, canvas_pose, pose_error
from bpp.drawing.procedural import ProceduralConfig, generate_drawing


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threshold", type=float, default=3.0, help="Chamfer (px) above which a demonstration fails")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    scene = Scene(image_size=96)
    physics = _time_physics(scene)
    scores, steps, seconds, physics_seconds, pose_mm, failures = [], [], [], [], [], Counter()
    photo = {"own drawing": [], "another drawing": []}  # (exact, from the photo)
    photo_refused = 0
    for i in range(args.n):
        drawing, _ = generate_drawing(np.random.default_rng([args.seed, i]), ProceduralConfig(), f"d{i}")
        truth = canvas_transform(rng.uniform(-0.25, 0.25), rng.uniform(-0.08, 0.08), rng.uniform(-45, 45))
        scene.reset(truth, ASIDE)
        camera = scene.camera_pose("scene")
        try:
            seen = canvas_pose(scene.render("scene", 640), scene.camera_intrinsics("scene", 640),
                               up=camera[:3, :3].T @ BOARD[:, 1])  # fmt: skip
        except CanvasNotFound as err:
            failures[f"no canvas pose ({err.reason})"] += 1
            continue
        measured = canvas_in_base(camera, seen)
        pose_mm.append(pose_error(measured, truth)[0] * 1000)
        scene.reset(truth, HOME_QPOS)
        plan = plan_drawing(drawing.strokes, rng, ScriptConfig(), CONTROL_HZ)
        start, physics_before = time.perf_counter(), physics["s"]
        recorded = execute(scene, measured, plan)
        seconds.append(time.perf_counter() - start)
        physics_seconds.append(physics["s"] - physics_before)
        # scored in the true canvas frame: the ink is where the pen touched the real canvas
        score = ink_chamfer(recorded.strokes, drawing.strokes)
        steps.append(len(recorded.actions))
        if score > args.threshold:
            failures[f"Chamfer over {args.threshold:g} px"] += 1
            continue
        scores.append(score)
        other, _ = generate_drawing(np.random.default_rng([args.seed, i + 1]), ProceduralConfig(), f"d{i + 1}")
        try:
            rectified = photograph_canvas(scene)
        except CanvasNotFound:
            photo_refused += 1
            continue
        for key, strokes in (("own drawing", drawing.strokes), ("another drawing", other.strokes)):
            photo[key].append((ink_chamfer(recorded.strokes, strokes), rectified_chamfer(rectified, strokes)))
    scene.close()
    scores = np.array(scores)
    print(f"{args.n} drawings (seed {args.seed}): {len(scores)} demonstrations kept, failures {dict(failures)}")
    p50, p95, top = np.percentile(scores, [50, 95, 100])
    print(f"| Chamfer of the kept demonstrations (px) | {p50:.2f} | {p95:.2f} | {top:.2f} |")
    mm = [pixels_to_mm(v) for v in (p50, p95, top)]
    print(f"| the same in mm on the canvas | {mm[0]:.2f} | {mm[1]:.2f} | {mm[2]:.2f} |")
    print(f"canvas pose error of the photos used (mm): p50 {np.median(pose_mm):.2f}, max {np.max(pose_mm):.2f}")
    print(f"Chamfer from a photo against the exact one ({photo_refused} photos gave no canvas pose):")
    print("| scored against | demonstrations | exact: median | photo: median | abs difference: median | p90 | max |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for key, pairs in photo.items():
        exact, seen = np.array(pairs).T
        diff = np.abs(seen - exact)
        print(f"| {key} | {len(pairs)} | {np.median(exact):.2f} | {np.median(seen):.2f} | {np.median(diff):.2f} | "
              f"{np.percentile(diff, 90):.2f} | {diff.max():.2f} |")  # fmt: skip
    rate = np.sum(steps) / CONTROL_HZ / np.sum(seconds)
    share = np.sum(physics_seconds) / np.sum(seconds)
    print(f"{np.mean(steps):.0f} control steps ({np.mean(steps) / CONTROL_HZ:.1f} s) per demonstration on average; "
          f"{np.mean(seconds):.2f} s of wall clock each: {rate:.1f}x real time (no camera rendered); MuJoCo's "
          f"physics alone {np.mean(physics_seconds):.2f} s ({share:.0%})")  # fmt: skip


def _time_physics(scene: Scene) -> dict:
    """Time every ``mj_step`` the scene calls: a stand-in module whose ``mj_step`` adds its seconds to the returned
    dict's "s"."""
    timed, step = {"s": 0.0}, scene.mujoco.mj_step

    def mj_step(model, data) -> None:
        start = time.perf_counter()
        step(model, data)
        timed["s"] += time.perf_counter() - start

    module = types.ModuleType("mujoco_timed")
    module.__dict__.update(vars(scene.mujoco))
    module.mj_step = mj_step
    scene.mujoco = module
    return timed


if __name__ == "__main__":
    main()
