"""Policy server memory under uploads: does what clients upload go when they leave?

The server runs in its own process, as `bpp serve` does, with a BPP model observing a 64 px camera (`cpu:image64`)
and the default upload limits (4 per connection, 1 GiB in all). Each round, `--clients` connections each upload
`--uploads` distinct demonstrations (random frames, `--steps` steps: 7 MiB each at 600 steps), then close. Printed
per round: the server's resident memory with the clients connected and after they left, and the size of the uploads
its prompt library holds.

    python bench/serve_uploads.py [--clients 8] [--uploads 6] [--steps 600] [--rounds 3]
"""

from __future__ import annotations

import argparse
import asyncio
import ctypes
import ctypes.util
import multiprocessing as mp
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def _rss_mib(pid: str = "self") -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _serve(store_path: str, ports, stats) -> None:
    """The server's process: serves on a free port (put on `ports`); answers each `stats` request with its resident
    memory, the bytes of the uploads it holds, and its resident memory once malloc has handed back what is free (what
    the allocator keeps for reuse is not held by the server)."""
    import torch

    from bpp.benchmarks.draw.benchmark import BENCHMARK
    from bpp.data.store import EpisodeStore
    from bpp.policies.registry import get_method
    from bpp.serve.prompts import PromptLibrary
    from bpp.serve.server import PolicyServer

    torch.set_num_threads(1)
    torch.manual_seed(0)
    store = EpisodeStore(store_path)
    method = get_method("bpp")
    model = method.model_cls(method.config("cpu", "image64", BENCHMARK), store.stats).eval()
    library = PromptLibrary(model.data_spec(), model.validate_context, store, BENCHMARK.frames)
    server = PolicyServer(model, library, {"method": "bpp"})

    libc = ctypes.CDLL(ctypes.util.find_library("c"))

    def answer() -> None:
        while stats.recv() is not None:
            rss, held = _rss_mib(), library.upload_bytes / 2**20
            libc.malloc_trim(0)
            stats.send((rss, held, _rss_mib()))

    threading.Thread(target=answer, daemon=True).start()
    asyncio.run(server.serve("127.0.0.1", 0, ports.put))


def _demonstration(spec, store, steps: int, seed: int) -> dict:
    """A demonstration of `steps` steps the served model takes: random camera frames, features and actions inside
    the store's ranges."""
    rng = np.random.default_rng(seed)
    size = spec.image_size

    def within(key: str) -> np.ndarray:
        low, high = (np.asarray(store.stats[key][k], np.float32) for k in ("min", "max"))
        return (low + rng.random((steps, low.size), dtype=np.float32) * (high - low)).astype(np.float32)

    obs = {k: within(k) for k in spec.lowdim_keys}
    obs |= {k: rng.integers(0, 256, (steps, size, size, 3), dtype=np.uint8) for k in spec.image_keys}
    return {"obs": obs, "action": within(spec.action_key)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--uploads", type=int, default=6, help="uploads per client and round")
    parser.add_argument("--steps", type=int, default=600, help="steps per uploaded demonstration")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()

    from bpp.benchmarks.draw.benchmark import BENCHMARK
    from bpp.benchmarks.draw.dataset import PRESETS, generate
    from bpp.policies.registry import get_method
    from bpp.serve.client import PolicyClient

    with tempfile.TemporaryDirectory() as tmp:
        store = generate(PRESETS["debug"], Path(tmp) / "prompts.zarr", workers=1, progress=False)
        method = get_method("bpp")
        spec = method.model_cls(method.config("cpu", "image64", BENCHMARK), store.stats).data_spec()
        context = mp.get_context("spawn")
        ports, (stats, theirs) = context.Queue(), context.Pipe()
        proc = context.Process(target=_serve, args=(str(store.path), ports, theirs), daemon=True)
        proc.start()
        url = f"ws://127.0.0.1:{ports.get(timeout=300)}"

        def measure() -> tuple[float, float, float]:
            time.sleep(1.0)  # the server lets a closed connection's uploads go once it has seen the close
            stats.send("stats")
            return stats.recv()

        rss, held, trimmed = measure()
        print(f"started: {rss:.0f} MiB resident ({trimmed:.0f} trimmed), {held:.1f} MiB of uploads held")
        print(
            "| round | uploads sent (MiB) | clients connected: resident, uploads held (MiB) "
            "| after they left: resident, uploads held, resident once malloc is trimmed |"
        )
        for round_ in range(args.rounds):
            clients = [PolicyClient(url) for _ in range(args.clients)]
            sent = 0
            for i, client in enumerate(clients):
                for k in range(args.uploads):
                    demo = _demonstration(spec, store, args.steps, seed=(round_ * args.clients + i) * args.uploads + k)
                    sent += sum(v.nbytes for v in demo["obs"].values()) + demo["action"].nbytes
                    client.infer({"upload": demo})
            during = measure()
            for client in clients:
                client.close()
            after = measure()
            cells = [f"{round_ + 1}", f"{sent / 2**20:.0f}", "{:.0f}, {:.0f}".format(*during[:2])]
            cells.append("{:.0f}, {:.0f}, {:.0f}".format(*after))
            print("| " + " | ".join(cells) + " |")
        stats.send(None)
        proc.kill()


if __name__ == "__main__":
    main()
