"""DrawAnything-Real's canvas pose from its red markers, over random placements: errors and failures.

Each placement puts the canvas 0.5-1.0 m from a 640x480 camera (f = 600 px), tilted up to 30 degrees and rotated
within +-45 degrees of upright, under a random exposure (0.5-1.3, plus a random brightness gradient and pixel noise);
every other one adds a dark occluder polygon (a hand, a pen, an arm's edge), half of those aimed at a marker. The
pose measured by ``canvas_pose`` is compared with the truth; a pose more than 1 cm or 2 degrees off is counted as
silently wrong, which must never happen. Prints markdown tables.

With ``--simulator N`` the photos come from the simulated arm's scene instead (MuJoCo, robosuite's Panda): N random
canvas placements on the board (±45 degrees), the light's strength varied, the arm either swung aside or standing
at a random pose in front of the board (where it may hide markers), the scene camera's photo at 480x480 and its
extrinsic calibration turning the pose into the robot's base frame, compared with the simulator's placement.

    python bench/draw3d_canvas_pose.py [--n 200] [--seed 0]
    python bench/draw3d_canvas_pose.py --simulator 100
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

import cv2
import numpy as np

from bpp.drawing.marked_canvas import (
    CanvasLayout,
    CanvasNotFound,
    canvas_pose,
    pose_error,
    random_canvas_pose,
    render_canvas,
)

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
SIZE = (640, 480)
WRONG_MM, WRONG_DEG = 10.0, 2.0


def project(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    cam = points @ pose[:3, :3].T + pose[:3, 3]
    return (cam @ K.T)[..., :2] / cam[..., 2:]


def random_occluder(rng: np.random.Generator, pose: np.ndarray, layout: CanvasLayout) -> np.ndarray:
    """(N, 2) pixel polygon: a blob (3-7 vertices, 8-60 px across) or a long bar (an arm or a pen), centred on a
    random marker half the time and anywhere in the image otherwise."""
    if rng.uniform() < 0.5:
        centre = project(pose, layout.marker_points()[rng.integers(4)]) + rng.normal(0, 10, 2)
    else:
        centre = rng.uniform((0, 0), SIZE)
    if rng.uniform() < 0.7:
        angles = np.sort(rng.uniform(0, 2 * np.pi, rng.integers(3, 8)))
        radii = rng.uniform(8, 60) * rng.uniform(0.5, 1.0, len(angles))
        return centre + np.c_[np.cos(angles), np.sin(angles)] * radii[:, None]
    direction = rng.normal(size=2)
    direction /= np.linalg.norm(direction)
    along, across = direction * 400, np.array([-direction[1], direction[0]]) * rng.uniform(3, 25)
    return centre + np.array([across, along + across, along - across, -across])


def hidden_fraction(pose: np.ndarray, layout: CanvasLayout, occluder: np.ndarray | None) -> float:
    """The largest fraction of one marker's image that `occluder` covers (rasterised at 4x)."""
    if occluder is None:
        return 0.0
    s, (w, h) = 4, SIZE
    cover = np.zeros((h * s, w * s), np.uint8)
    cv2.fillPoly(cover, [np.rint(s * (occluder + 0.5) - 0.5).astype(np.int32)], 1)
    worst = 0.0
    for square in project(pose, layout.marker_corners()):
        marker = np.zeros_like(cover)
        cv2.fillPoly(marker, [np.rint(s * (square + 0.5) - 0.5).astype(np.int32)], 1)
        worst = max(worst, float((marker & cover).sum()) / max(int(marker.sum()), 1))
    return worst


def stats(values: list[float]) -> str:
    if not values:
        return "- / - / -"
    p50, p95, top = np.percentile(values, [50, 95, 100])
    return f"{p50:.2f} / {p95:.2f} / {top:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=200, help="random placements")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--simulator", type=int, default=0, help="placements in the simulated scene instead")
    args = parser.parse_args()
    if args.simulator:
        simulator(args.simulator, args.seed)
        return
    rng, layout = np.random.default_rng(args.seed), CanvasLayout()
    rows: dict[str, list] = {"no occluder": [], "occluder, no marker hidden": [], "occluder over a marker": []}
    failures: dict[str, Counter] = {group: Counter() for group in rows}
    examples: dict[str, str] = {}
    seconds = []
    for i in range(args.n):
        truth = random_canvas_pose(rng, K, SIZE)
        occluder = random_occluder(rng, truth, layout) if i % 2 else None
        image = render_canvas(truth, K, SIZE, light=rng.uniform(0.5, 1.3), occluder=occluder, rng=rng)
        hidden = hidden_fraction(truth, layout, occluder)
        group = "no occluder" if occluder is None else "occluder over a marker" if hidden > 0 else list(rows)[1]
        start = time.perf_counter()
        try:
            estimate = canvas_pose(image, K, layout)
        except CanvasNotFound as err:
            failures[group][err.reason] += 1
            examples.setdefault(err.reason, str(err))
            rows[group].append(None)
            continue
        finally:
            seconds.append(time.perf_counter() - start)
        position, rotation = pose_error(estimate, truth)
        rows[group].append((position * 1000, rotation, hidden))

    print(f"Canvas pose from its red markers: {args.n} random placements (seed {args.seed}), 640x480, f = 600 px, ")
    print(f"canvas_pose {1000 * np.median(seconds):.0f} ms per image (median).\n")
    print("| placements | n | poses | failures | position p50 / p95 / max (mm) | rotation p50 / p95 / max (deg) "
          f"| wrong (> {WRONG_MM:.0f} mm or > {WRONG_DEG:.0f} deg) |")  # fmt: skip
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    every = [r for group in rows.values() for r in group]
    for name, group in [*rows.items(), ("all", every)]:
        poses = [r for r in group if r is not None]
        wrong = sum(p > WRONG_MM or d > WRONG_DEG for p, d, _ in poses)
        print(
            f"| {name} | {len(group)} | {len(poses)} | {len(group) - len(poses)} | {stats([p for p, _, _ in poses])} "
            f"| {stats([d for _, d, _ in poses])} | {wrong} |"
        )
    partly = [r for r in rows["occluder over a marker"] if r is not None and r[2] > 0]
    if partly:
        print(f"\nPoses despite a partly hidden marker: {len(partly)}, hiding up to {max(r[2] for r in partly):.0%} "
              f"of a marker; position max {max(r[0] for r in partly):.2f} mm, rotation max "
              f"{max(r[1] for r in partly):.2f} deg.")  # fmt: skip
    print("\n| failure | no occluder | occluder, no marker hidden | occluder over a marker | example |")
    print("| --- | ---: | ---: | ---: | --- |")
    for reason in sorted(examples):
        counts = " | ".join(str(failures[group][reason]) for group in rows)
        print(f"| {reason} | {counts} | {examples[reason]} |")


def simulator(n: int, seed: int) -> None:
    from bpp.benchmarks.draw3d.demonstrator import ScriptConfig, random_pose
    from bpp.benchmarks.draw3d.scene import BOARD, HOME_QPOS, Scene, canvas_transform
    from bpp.core.poses import invert, pose_to_vector
    from bpp.drawing.marked_canvas import canvas_in_base

    rng = np.random.default_rng(seed)
    scene = Scene(image_size=96)
    light = scene.model.light_diffuse[0].copy()
    from bpp.benchmarks.draw3d.dataset import ASIDE

    rows: dict[str, list] = {"arm swung aside": [], "arm in front of the board": []}
    failures: dict[str, Counter] = {group: Counter() for group in rows}
    examples: dict[str, str] = {}
    size = 640
    for i in range(n):
        truth = canvas_transform(rng.uniform(-0.25, 0.25), rng.uniform(-0.08, 0.08), rng.uniform(-45, 45))
        scene.model.light_diffuse[0] = light * rng.uniform(0.5, 1.3)
        in_front = bool(i % 2)
        scene.reset(truth, HOME_QPOS if in_front else ASIDE)
        if in_front:  # walk the pen to a random pose in front of the canvas, as a demonstration starts
            goal = truth @ random_pose(rng, ScriptConfig())
            start = scene.target.copy()
            for k in range(1, 21):
                a = k / 20
                waypoint = goal.copy()
                waypoint[:3, 3] = (1 - a) * start[:3, 3] + a * goal[:3, 3]
                scene.step(np.append(pose_to_vector(invert(scene.target) @ waypoint), 0.0))
        group = list(rows)[in_front]
        camera = scene.camera_pose("scene")
        try:
            found = canvas_pose(
                scene.render("scene", size), scene.camera_intrinsics("scene", size), up=camera[:3, :3].T @ BOARD[:, 1]
            )
        except CanvasNotFound as err:
            failures[group][err.reason] += 1
            examples.setdefault(err.reason, str(err))
            rows[group].append(None)
            continue
        position, rotation = pose_error(canvas_in_base(camera, found), truth)
        rows[group].append((position * 1000, rotation, 0.0))
    scene.close()
    print(f"Canvas pose in the simulated scene: {n} placements (seed {seed}), scene camera 640x640, light x0.5-1.3\n")
    print("| arm | n | poses | failures | position p50 / p95 / max (mm) | rotation p50 / p95 / max (deg) "
          f"| wrong (> {WRONG_MM:.0f} mm or > {WRONG_DEG:.0f} deg) |")  # fmt: skip
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for name, group in rows.items():
        poses = [r for r in group if r is not None]
        wrong = sum(p > WRONG_MM or d > WRONG_DEG for p, d, _ in poses)
        print(
            f"| {name} | {len(group)} | {len(poses)} | {len(group) - len(poses)} | {stats([p for p, _, _ in poses])} "
            f"| {stats([d for _, d, _ in poses])} | {wrong} |"
        )
    for reason in sorted(examples):
        counts = ", ".join(f"{group}: {failures[group][reason]}" for group in rows)
        print(f"\nfailure {reason} ({counts}), e.g.: {examples[reason]}")


if __name__ == "__main__":
    main()
