"""iPhUMI processing against ground truth, its speed, and the prompt hand-off to a served policy.

1. Accuracy: a synthetic export (app format, known motion) is processed; per step, the TCP pose and gripper width
   are compared with the synthetic motion at the step's time: position (mm), rotation (deg), width (mm), and the
   alignment error (ms): the time shift of the true motion that best explains the processed positions. A bimanual
   export measures the second arm the same way.
2. Speed: recording seconds processed per wall-clock second (`bpp iphumi process`, one worker per core), with the
   main camera at the synthetic 160x120 and at the app's 1920x1440, calibrations measured afresh (no cache). The
   anchor, same run: FFmpeg alone (the binary the processing decodes with) decoding the same videos to nothing, one
   process per core.
3. Hand-off: `bpp iphumi prompt` to a `bpp serve` on loopback (BPP, cpu preset, the wrist camera observation;
   weights barely trained, since latency does not depend on them): processing, upload and first action; the upload's
   anchor, same run: the `websockets` library alone on loopback echoing a message of the same size.

    python bench/iphumi.py [--demonstrations 6] [--large-demonstrations 2]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from bpp.benchmarks.iphumi.pipeline import process_export
from bpp.benchmarks.iphumi.process import ProcessSettings
from bpp.benchmarks.iphumi.synthetic import SyntheticSettings, write_export
from bpp.core.poses import invert, rotation_angle, vector_to_pose
from transport import transport_floor


def accuracy(root: Path, settings: SyntheticSettings, arms: tuple[str, ...]) -> dict:
    truths = write_export(root / "export", settings)
    store, _, rejected = process_export(root / "export", root / "store.zarr", workers=2, progress=False)
    assert not rejected, rejected
    errors = {"position_mm": [], "rotation_deg": [], "width_mm": [], "shift_ms": []}
    fps = store.config["fps"]
    for episode in range(store.num_episodes):
        group = store.config["demonstrations"][episode]
        start = float(store.column("start_s")[episode])
        reference = truths[f"{group}_right"]
        for prefix, side in zip(("", "arm1_"), arms, strict=False):
            truth = truths[f"{group}_{side}"]
            got = store.episode(episode, [f"{prefix}pose", f"{prefix}width"])
            n = len(got[f"{prefix}width"])
            times = reference.times[0] + start + np.arange(n) / fps
            origin = invert(reference.motion(times[:1])[0][0])
            tcp, width = truth.motion(times)
            expected = origin @ tcp
            pose = vector_to_pose(got[f"{prefix}pose"].astype(np.float64))
            errors["position_mm"].append(np.linalg.norm(pose[:, :3, 3] - expected[:, :3, 3], axis=1) * 1e3)
            errors["rotation_deg"].append(np.rad2deg(rotation_angle(pose[:, :3, :3], expected[:, :3, :3])))
            errors["width_mm"].append(np.abs(got[f"{prefix}width"][:, 0] - width) * 1e3)
            shifts = np.arange(-8.0, 8.01, 0.1) * 1e-3
            cost = [np.mean(np.linalg.norm(pose[:, :3, 3] - (origin @ truth.motion(times + s)[0])[:, :3, 3], axis=1))
                    for s in shifts]  # fmt: skip
            errors["shift_ms"].append(np.array([abs(shifts[int(np.argmin(cost))]) * 1e3]))
    return {k: np.concatenate(v) for k, v in errors.items()} | {"steps": store.num_steps}


def speed(root: Path, settings: SyntheticSettings) -> tuple[float, float, float]:
    """(recording seconds, processing's wall seconds, FFmpeg's alone on the same videos)."""
    truths = write_export(root / "export", settings)
    seconds = sum(t.times[-1] - t.times[0] for t in truths.values())
    t0 = time.perf_counter()
    process_export(root / "export", root / "store.zarr", workers=2, progress=False)
    wall = time.perf_counter() - t0
    return seconds, wall, decoding_alone(sorted((root / "export").rglob("*.mp4")), workers=2)


def decoding_alone(videos: list[Path], workers: int) -> float:
    """Wall seconds FFmpeg takes to decode `videos` to nothing, `workers` processes at a time, one thread each."""
    # imageio-ffmpeg: the FFmpeg binary the processing reads videos with
    import imageio_ffmpeg

    def decode(video: Path) -> None:
        command = [imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-threads", "1", "-i", str(video), "-f", "null", "-"]
        subprocess.run(command, check=True, capture_output=True)

    t0 = time.perf_counter()
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(decode, videos))
    return time.perf_counter() - t0


def hand_off_latency(root: Path, repeats: int) -> list:
    from bpp.benchmarks.iphumi.prompt import hand_off
    from bpp.benchmarks.iphumi.recording import find_recordings
    from bpp.cli import main
    from bpp.serve.command import build_server
    from bpp.serve.server import ServerThread

    write_export(root / "export", SyntheticSettings(demonstrations=4, tasks=2, seed=7))
    process_export(root / "export", root / "store.zarr", workers=2, progress=False)
    main(["train", "--method", "bpp", "--preset", "cpu", "--obs", "wrist", "--data", str(root / "store.zarr"),
          "--out", str(root / "run"), "--steps", "2", "--batch-size", "4", "--workers", "0"])  # fmt: skip
    recording = next(f for f in find_recordings(root / "export") if "demonstration" in f.name)
    results, command = [], []
    with ServerThread(build_server(root / "run", str(root / "store.zarr"))) as url:
        for _ in range(repeats):
            results.append(hand_off(recording, url, settings=ProcessSettings()))
        for _ in range(2):  # the whole command, as a person runs it: Python's start and imports included
            t0 = time.perf_counter()
            cli = [sys.executable, "-m", "bpp.cli", "iphumi", "prompt", str(recording), "--server", url]
            subprocess.run(cli, check=True, capture_output=True)
            command.append(time.perf_counter() - t0)
    return results, command


def _row(name: str, values: np.ndarray) -> str:
    p50, p95, top = np.percentile(values, [50, 95, 100])
    return f"| {name} | {p50:.3f} | {p95:.3f} | {top:.3f} |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demonstrations", type=int, default=6)
    parser.add_argument("--large-demonstrations", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--parts", nargs="+", default=["accuracy", "speed", "handoff"])
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        if "accuracy" in args.parts:
            report_accuracy(root, args)
        if "speed" in args.parts:
            report_speed(root, args)
        if "handoff" in args.parts:
            report_handoff(root, args)


def report_accuracy(root: Path, args) -> None:
    single = SyntheticSettings(demonstrations=args.demonstrations, tasks=3, tasks_per_demonstration=2, seed=11)
    one = accuracy(root / "single", single, ("right",))
    bimanual = SyntheticSettings(demonstrations=max(2, args.demonstrations // 3), tasks=2, bimanual=True, seed=12)
    two = accuracy(root / "bimanual", bimanual, ("right", "left"))
    print(f"accuracy ({one['steps']} single-arm steps, {two['steps']} bimanual steps at 10 Hz): p50 | p95 | max")
    print("| quantity | p50 | p95 | max |\n| --- | ---: | ---: | ---: |")
    for key in ("position_mm", "rotation_deg", "width_mm", "shift_ms"):
        print(_row(f"single arm, {key}", one[key]))
        print(_row(f"bimanual (both arms), {key}", two[key]))


def report_speed(root: Path, args) -> None:
    # A first processing: each export's gripper calibrations measured, not read from an earlier run's cache.
    before = os.environ.get("BPP_CACHE")
    os.environ["BPP_CACHE"] = str(root / "cache")  # read by each call's new worker processes
    try:
        small = speed(root / "small", SyntheticSettings(demonstrations=args.demonstrations, tasks=3, seed=13))
        large = speed(root / "large", SyntheticSettings(demonstrations=args.large_demonstrations, tasks=2, seed=14,
                                                        main_size=(1920, 1440)))  # fmt: skip
    finally:
        if before is None:
            os.environ.pop("BPP_CACHE")
        else:
            os.environ["BPP_CACHE"] = before
    for name, (seconds, wall, ffmpeg) in (("160x120 main camera", small), ("1920x1440 main camera", large)):
        print(
            f"speed, {name}: {seconds:.0f} s of recording in {wall:.1f} s: {seconds / wall:.2f} recording s per s; "
            f"FFmpeg decoding its videos alone {ffmpeg:.1f} s: {seconds / ffmpeg:.2f}; processing at "
            f"{ffmpeg / wall:.0%} of it"
        )


def report_handoff(root: Path, args) -> None:
    results, command = hand_off_latency(root / "prompt", args.repeats)
    for name in ("process_s", "upload_s", "first_action_s"):
        values = np.array([getattr(r, name) for r in results]) * 1e3
        print(f"hand-off {name}: p50 {np.median(values):.0f} ms, max {values.max():.0f} ms")
    floor = np.array(transport_floor(results[0].upload_bytes, 64, args.repeats))
    print(f"the transport alone (websockets, as many bytes): p50 {np.median(floor):.1f} ms, max {floor.max():.1f} ms")
    print(f"the whole command: {', '.join(f'{s:.2f}' for s in command)} s")
    print(f"hand-off upload size: {results[0].upload_bytes / 1024:.0f} KiB, {results[0].steps} steps")


if __name__ == "__main__":
    main()
