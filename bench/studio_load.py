"""A bounded load test of the studio on loopback: N concurrent clients for D seconds.

    python bench/studio_load.py --clients 20 --seconds 60 [--run runs/demo-bpp]

Starts ``bpp studio --no-browser`` in a subprocess (on a trained run: --run, else a 2-step debug run trained here),
then runs each client in its own thread and from its own loopback address (127.0.0.2, 127.0.0.3, ...: the studio
counts sessions per client address, as it would count users on separate machines). Each repeats: upload a prompt
(a random triangle, demonstrated by the server), start a rollout of --max-steps steps at a random angle, read its
event stream to the end. Records the latency of every API call, the time to a rollout's first step event, the gap
between step events, completed rollouts and every error (any non-2xx answer or broken stream; 429 "at capacity"
answers are counted apart and retried after a pause, since refusing work over the limit is the server doing its
job).
"""

from __future__ import annotations

import argparse
import os
import random
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from bpp.benchmarks.draw.studio.client import StudioClient, StudioClientError

TOKEN = "load-test-token-0123456789"


def debug_run(folder: Path) -> Path:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    store, run = folder / "debug.zarr", folder / "runs" / "debug"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "bpp.cli",
            "draw",
            "generate",
            "--preset",
            "debug",
            "--workers",
            "1",
            "--out",
            str(store),
        ],
        check=True,
        env=env,
        capture_output=True,
    )
    subprocess.run(
        [
            sys.executable,
            "-m",
            "bpp.cli",
            "train",
            "--data",
            str(store),
            "--out",
            str(run),
            "--preset",
            "debug",
            "--steps",
            "2",
            "--workers",
            "0",
        ],
        check=True,
        env=env,
        capture_output=True,
    )
    return run.parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clients", type=int, default=20)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--max-steps", type=int, default=100, help="steps per rollout")
    parser.add_argument("--run", type=Path, default=None, help="a trained run (default: a debug run trained here)")
    args = parser.parse_args()
    if not 1 <= args.clients <= 250:
        parser.error("--clients must be 1 to 250 (one loopback address each)")
    with tempfile.TemporaryDirectory(prefix="studio-load-") as tmp:
        runs = args.run if args.run else debug_run(Path(tmp))
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        server = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "bpp.cli",
                "studio",
                "--no-browser",
                "--runs",
                str(runs),
                "--port",
                str(port),
                "--token",
                TOKEN,
                "--max-rollouts",
                str(args.clients),
                "--data-dir",
                str(Path(tmp) / "data"),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        url = f"http://127.0.0.1:{port}"
        try:
            _wait(url)
            stats = _load(url, args)
        finally:
            server.terminate()
            server.wait(timeout=30)
    _print(stats, args)


def _wait(url: str, timeout: float = 120.0) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline:
        try:
            StudioClient(url, TOKEN).close()
            return
        except Exception:  # noqa: BLE001 - not up yet
            time.sleep(0.5)
    raise SystemExit("the studio did not start")


def _load(url: str, args) -> dict:
    stats: dict = defaultdict(list)
    lock = threading.Lock()
    stop_at = time.time() + args.seconds

    def record(key, value):
        with lock:
            stats[key].append(value)

    def timed(key, call):  # answered calls only: refusals (429) are counted apart
        t0 = time.perf_counter()
        result = call()
        record(key, time.perf_counter() - t0)
        return result

    def client(index: int) -> None:
        rng = random.Random(index)
        try:
            address = f"127.0.0.{2 + index}"
            c = timed("session", lambda: StudioClient(url, TOKEN, local_address=address))
            checkpoint = c.checkpoints()[0]["id"]
        except Exception as err:  # noqa: BLE001
            record("errors", f"client {index}: {type(err).__name__}: {err}")
            return
        while time.time() < stop_at:
            try:
                triangle = [[[rng.uniform(0.1, 0.9), rng.uniform(0.1, 0.9)] for _ in range(3)]]
                prompt = timed("prompt", lambda t=triangle: c.prompt_strokes(t, rng.uniform(-0.7, 0.7), index))
                angle = rng.uniform(-0.7, 0.7)
                rollout = timed(
                    "rollout start", lambda p=prompt, a=angle: c.rollout(p["id"], checkpoint, a, index, args.max_steps)
                )
                t0 = last = time.perf_counter()
                first, end = True, None
                for event in c.events(rollout["id"]):
                    now = time.perf_counter()
                    if event["type"] == "step":
                        record("first step" if first else "step gap", now - (t0 if first else last))
                        first, last = False, now
                    elif event["type"] == "end":
                        end = event
                if end is None or end["status"] != "done":
                    record("errors", f"client {index}: rollout ended {end}")
                else:
                    record("rollouts", time.perf_counter() - t0)
            except StudioClientError as err:
                if err.status == 429:
                    record("at capacity (429)", 1)
                    time.sleep(0.5)
                else:
                    record("errors", f"client {index}: {err}")
            except Exception as err:  # noqa: BLE001
                record("errors", f"client {index}: {type(err).__name__}: {err}")
        c.close()

    threads = [threading.Thread(target=client, args=(i,)) for i in range(args.clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return stats


def _print(stats: dict, args) -> None:
    print(f"{args.clients} clients for {args.seconds:.0f} s, {args.max_steps}-step rollouts")
    print("| measure | count | p50 | p90 | p99 | max |")
    print("|---|---:|---:|---:|---:|---:|")
    labels = {
        "session": "new session",
        "prompt": "prompt upload (demonstrated and stored by the server)",
        "rollout start": "rollout start",
        "first step": "first step event after the start",
        "step gap": "gap between step events as delivered (the stream sends what is new every 20 ms)",
        "rollouts": "whole rollout, start to end event",
    }
    for key, label in labels.items():
        values = np.array(stats.get(key, []))
        if len(values):
            p50, p90, p99 = np.percentile(values, [50, 90, 99])
            print(f"| {label} (s) | {len(values)} | {p50:.3f} | {p90:.3f} | {p99:.3f} | {values.max():.3f} |")
    print(f"at capacity (429, retried): {len(stats.get('at capacity (429)', []))}")
    errors = stats.get("errors", [])
    print(f"errors: {len(errors)}")
    for line in errors[:20]:
        print("  " + line)


if __name__ == "__main__":
    main()
