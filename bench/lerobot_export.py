"""`bpp lerobot export` and `import` on a DrawAnything store: frames a second, against LeRobot's own code in the run.

The anchor is LeRobot's dataset writer: the export's calls into it (`LeRobotDataset.create`, `add_frame`,
`save_episode` with its video encoding, `finalize`) are timed inside the same export, so the rest of the wall time is
bpp's (reading the store, drawing the camera frames, checks). The import is timed whole; its anchor is PyAV (the
decoder it reads the videos with) decoding the dataset's videos alone, after it, in the same run.

Runs in LeRobot's environment:

    OMP_NUM_THREADS=1 .venv-lerobot/bin/python bench/lerobot_export.py [--tasks 40 --demos 4 --image-size 32]
"""

from __future__ import annotations

import argparse
import contextlib
import tempfile
import time
from collections import defaultdict
from pathlib import Path

from bpp.benchmarks.lerobot.export import export_store
from bpp.benchmarks.lerobot.importer import import_dataset
from bpp.benchmarks.lerobot.library import dataset_library
from bpp.cli import main as bpp
from bpp.core.registry import open_store

WRITER = ("create", "add_frame", "save_episode", "finalize")


@contextlib.contextmanager
def timed(cls, names: tuple[str, ...], seconds: dict[str, float]):
    """Add the wall seconds each of `cls`'s methods `names` takes to `seconds[name]` while the block runs (an outer
    call only: a method calling another of them is not counted twice)."""
    originals = {name: cls.__dict__[name] for name in names}
    depth = [0]

    def wrap(name, function):
        def wrapper(*args, **kwargs):
            depth[0] += 1
            t0 = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                depth[0] -= 1
                if depth[0] == 0:
                    seconds[name] += time.perf_counter() - t0

        return wrapper

    for name, original in originals.items():
        if isinstance(original, classmethod):
            setattr(cls, name, classmethod(wrap(name, original.__func__)))
        else:
            setattr(cls, name, wrap(name, original))
    try:
        yield
    finally:
        for name, original in originals.items():
            setattr(cls, name, original)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", type=int, default=40)
    parser.add_argument("--demos", type=int, default=4)
    parser.add_argument("--image-size", type=int, default=32)
    parser.add_argument("--vcodec", default="libsvtav1")
    args = parser.parse_args()
    lib = dataset_library()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        bpp(["draw", "generate", "--preset", "debug", "--num-tasks", str(args.tasks), "--demos-per-task",
             str(args.demos), "--out", str(root / "store.zarr"), "--workers", "1"])  # fmt: skip
        store = open_store(root / "store.zarr")
        writer: dict[str, float] = defaultdict(float)
        t0 = time.perf_counter()
        with timed(lib.LeRobotDataset, WRITER, writer):
            export_store(store, root / "export", cameras=["image"], image_size=args.image_size, vcodec=args.vcodec,
                         progress=False)  # fmt: skip
        wall = time.perf_counter() - t0
        report("export", store.num_steps, wall, writer)
        t0 = time.perf_counter()
        import_dataset(root / "export", root / "back.zarr", progress=False)
        wall = time.perf_counter() - t0
        decoded, seconds = decoding_alone(sorted((root / "export").rglob("*.mp4")))
        print(
            f"import: {store.num_steps} frames in {wall:.1f} s ({store.num_steps / wall:.0f} frames/s); PyAV decoding "
            f"the {decoded} video frames alone {seconds:.2f} s ({decoded / seconds:.0f} frames/s), "
            f"{seconds / wall:.0%} of the import's time"
        )


def report(what: str, frames: int, wall: float, lerobot: dict[str, float]) -> None:
    inside = sum(lerobot.values())
    calls = ", ".join(f"{name} {seconds:.1f} s" for name, seconds in lerobot.items())
    print(
        f"{what}: {frames} frames in {wall:.1f} s ({frames / wall:.0f} frames/s); inside LeRobot's LeRobotDataset "
        f"{inside:.1f} s ({inside / wall:.0%}: {calls}); the rest, bpp's, {wall - inside:.1f} s"
    )


def decoding_alone(videos: list[Path]) -> tuple[int, float]:
    """(frames, wall seconds) of PyAV decoding every frame of `videos` to RGB arrays, one after another."""
    # PyAV: the lerobot extra
    import av

    frames, t0 = 0, time.perf_counter()
    for video in videos:
        with av.open(str(video)) as container:
            for frame in container.decode(video=0):
                frame.to_ndarray(format="rgb24")
                frames += 1
    return frames, time.perf_counter() - t0


if __name__ == "__main__":
    main()
