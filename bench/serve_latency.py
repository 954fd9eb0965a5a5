"""Policy server latency and throughput: `bpp serve` on loopback against in-process inference.

For each setting (a BPP size preset with an observation preset: state only, or cameras whose frames travel in every
request), the server runs in its own process, as `bpp serve` does:

* in process: one inference call of the agent (a chunk), p50 / p95;
* over the socket: one client's `infer` round trip (one observation step per request), p50 / p95, and so the
  protocol's overhead;
* the anchor, the transport alone: the `websockets` library's own server and client, no bpp code, echoing a reply
  of the served reply's size to a request of the served request's size, p50 / p95 (in its own process, as the
  server is);
* 1, 4 and 16 concurrent clients sending requests back to back: requests per second, p50 / p95 round trip and the
  mean batch the server formed;
* memory: the server's resident memory per connected client with a started episode (16 clients).

Untrained weights: the compute is that of a trained model of the same preset.

    python bench/serve_latency.py [--settings cpu:canvas cpu:image64 paper:paper] [--requests 40]
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from transport import transport_floor


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _model(size: str, obs: str, store):
    import torch

    from bpp.benchmarks.draw.benchmark import BENCHMARK
    from bpp.policies.registry import get_method

    torch.manual_seed(0)
    method = get_method("bpp")
    return method.model_cls(method.config(size, obs, BENCHMARK), store.stats).eval()


def _serve(size: str, obs: str, store_path: str, threads: int, ports) -> None:
    import torch

    from bpp.benchmarks.draw.benchmark import BENCHMARK
    from bpp.data.store import EpisodeStore
    from bpp.serve.prompts import PromptLibrary
    from bpp.serve.server import PolicyServer

    torch.set_num_threads(threads)
    store = EpisodeStore(store_path)
    model = _model(size, obs, store)
    library = PromptLibrary(model.data_spec(), model.validate_context, store, BENCHMARK.frames)
    server = PolicyServer(model, library, {"method": "bpp"})
    asyncio.run(server.serve("127.0.0.1", 0, ports.put))


def _observation(store, spec, episode: int, step: int) -> dict:
    from bpp.benchmarks.draw.benchmark import BENCHMARK

    sl = store.episode_slice(episode)
    obs = {k: store.array(k)[sl.start + step] for k in spec.lowdim_keys}
    for key in spec.image_keys:
        obs[key] = BENCHMARK.frames(store, episode, key, spec.image_size, steps=np.array([step]))[0]
    return obs


def _percentiles(ms: list[float]) -> tuple[float, float]:
    return float(np.percentile(ms, 50)), float(np.percentile(ms, 95))


def in_process(size: str, obs: str, store, requests: int, threads: int) -> list[float]:
    import torch

    from bpp.benchmarks.draw.benchmark import BENCHMARK
    from bpp.data.contexts import task_context
    from bpp.policies.agent import PolicyAgent

    torch.set_num_threads(threads)
    agent = PolicyAgent(_model(size, obs, store), record_attention=True)  # the arithmetic `bpp eval` and the server use
    agent.reset(task_context(store, 0, agent.data_spec, BENCHMARK.frames), seed=0)
    agent.act(_observation(store, agent.data_spec, 0, 0))
    times = []
    for _ in range(requests + 2):
        t0 = time.perf_counter()
        agent.predict_chunk()
        times.append(1e3 * (time.perf_counter() - t0))
    return times[2:]


def clients_run(url: str, store, spec, clients: int, requests: int) -> dict:
    """`clients` connections, each sending `requests` one-step requests back to back (after one that starts its
    episode); the round trips and the wall time of all of them."""
    from bpp.serve.client import PolicyClient

    conns = [PolicyClient(url) for _ in range(clients)]
    obs = [_observation(store, spec, i % store.num_episodes, 0) for i in range(clients)]
    for i, c in enumerate(conns):
        c.infer({**obs[i], "prompt": i % store.num_episodes, "seed": i})
    times: list[list[float]] = [[] for _ in range(clients)]
    batches: list[list[int]] = [[] for _ in range(clients)]
    barrier = threading.Barrier(clients + 1)

    def work(i: int) -> None:
        barrier.wait()
        for _ in range(requests):
            t0 = time.perf_counter()
            reply = conns[i].infer(obs[i])
            times[i].append(1e3 * (time.perf_counter() - t0))
            batches[i].append(int(reply["server_timing"]["batch"]))

    threads = [threading.Thread(target=work, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    barrier.wait()
    t0 = time.perf_counter()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    for c in conns:
        c.close()
    flat = [x for row in times for x in row]
    p50, p95 = _percentiles(flat)
    return {
        "clients": clients,
        "requests_per_s": clients * requests / wall,
        "p50_ms": p50,
        "p95_ms": p95,
        "mean_batch": float(np.mean([b for row in batches for b in row])),
    }


def memory_per_client(url: str, pid: int, store, spec, clients: int) -> float:
    """The server's resident memory growth per connection with a started episode, in KB."""
    from bpp.serve.client import PolicyClient

    before = _rss_mb(pid)
    conns = [PolicyClient(url) for _ in range(clients)]
    for i, c in enumerate(conns):
        c.infer({**_observation(store, spec, i % store.num_episodes, 0), "prompt": i % store.num_episodes})
    per_client = 1024 * (_rss_mb(pid) - before) / clients
    for c in conns:
        c.close()
    return per_client


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--settings", nargs="+", default=["debug:canvas", "cpu:canvas", "cpu:image64", "paper:canvas", "paper:paper"]
    )
    parser.add_argument("--requests", type=int, default=40, help="requests per client and measurement")
    parser.add_argument("--concurrency", type=int, nargs="+", default=[1, 4, 16])
    parser.add_argument("--threads", type=int, default=2, help="torch threads of the model")
    args = parser.parse_args()

    from bpp.benchmarks.draw.dataset import PRESETS, generate

    with tempfile.TemporaryDirectory() as tmp:
        store = generate(PRESETS["debug"], Path(tmp) / "prompts.zarr", workers=1, progress=False)
        print("| setting | in process p50 / p95 (ms) | socket p50 / p95 (ms) |", end=" ")
        print("transport alone p50 / p95 (ms) | request / reply bytes |", end=" ")
        print(" | ".join(f"{k} clients: req/s, p50 / p95 ms, batch" for k in args.concurrency), "| KB per client |")
        for setting in args.settings:
            size, obs = setting.split(":")
            requests = args.requests if size != "paper" else max(4, args.requests // 8)
            local = in_process(size, obs, store, requests, args.threads)
            ports: mp.Queue = mp.get_context("spawn").Queue()
            proc = mp.get_context("spawn").Process(
                target=_serve, args=(size, obs, str(store.path), args.threads, ports), daemon=True
            )
            proc.start()
            url = f"ws://127.0.0.1:{ports.get(timeout=300)}"
            try:
                spec = _model(size, obs, store).data_spec()
                from bpp.serve.client import PolicyClient
                from bpp.serve.wire import pack

                first = _observation(store, spec, 0, 0)
                size_bytes = len(pack(first))
                probe = PolicyClient(url)
                reply_bytes = len(pack(probe.infer({**first, "prompt": 0, "seed": 0})))
                probe.close()
                single = clients_run(url, store, spec, 1, requests)
                rows = [clients_run(url, store, spec, k, max(2, requests // k)) for k in args.concurrency]
                mem = memory_per_client(url, proc.pid, store, spec, 16)
            finally:
                proc.terminate()
                proc.join()
            lp50, lp95 = _percentiles(local)
            fp50, fp95 = _percentiles(transport_floor(size_bytes, reply_bytes, requests))
            cells = " | ".join(
                f"{r['requests_per_s']:.1f}, {r['p50_ms']:.0f} / {r['p95_ms']:.0f}, {r['mean_batch']:.1f}" for r in rows
            )
            print(
                f"| bpp {size} / {obs} | {lp50:.1f} / {lp95:.1f} | {single['p50_ms']:.1f} / {single['p95_ms']:.1f} | "
                f"{fp50:.2f} / {fp95:.2f} | {size_bytes:,} / {reply_bytes:,} | {cells} | {mem:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
