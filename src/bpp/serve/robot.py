"""The robot side of ``bpp serve``: a benchmark's simulated robots driven by a policy server, through openpi's
client where installed, under the evaluation protocol of ``bpp eval``.

``python -m bpp.serve.robot --server ws://HOST:PORT --tasks STORE`` (or ``bpp robot-client``) runs the protocol's
rollouts of each task in lockstep, one websocket connection per rollout (as many robots at once), and prints and
writes the same summary as ``bpp eval``. It imports no torch: a robot computer needs numpy, the benchmark's
simulator and the websocket client only. Served the same checkpoint, prompts and seeds, it reproduces ``bpp eval``'s
actions and scores (up to float sums, which differ with the batch size; BENCHMARKS.md measures the difference).
"""

from __future__ import annotations

import json
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import tyro
from tqdm import tqdm

from bpp.core.registry import get_benchmark, open_store
from bpp.data.spec import DataSpec
from bpp.errors import UserError
from bpp.evaluation.protocol import Protocol, TaskResult, results_json, rollout_rows
from bpp.serve.client import close, connect


def spec_from_metadata(meta: dict) -> DataSpec:
    """What the served policy observes, as the :class:`DataSpec` a benchmark's runner reads."""
    obs = meta["observation"]
    images = tuple(k for k, v in obs.items() if v["dtype"] == "uint8")
    size = obs[images[0]]["shape"][0] if images else 96
    return DataSpec(
        lowdim_keys=tuple(k for k in obs if k not in images),
        image_keys=images,
        image_size=int(size),
        action_key=meta["action"]["key"],
        n_obs_steps=int(meta["n_obs_steps"]),
        horizon=int(meta["horizon"]),
        context=meta["context"],
    )


class RemoteAgent:
    """The part of :class:`bpp.policies.agent.PolicyAgent` a benchmark's runner uses (``data_spec``, ``obs_keys``,
    ``n_action_steps``, ``act_batch``), answered by a policy server: rollout i talks over its own connection.

    Each rollout sends the observations of every step since its last request and executes the first
    ``n_action_steps`` actions of each reply, which is what ``bpp eval`` does in process.
    """

    def __init__(self, url: str, api_key: str | None = None, use_openpi: bool | None = None):
        self.url, self.api_key, self.use_openpi = url, api_key, use_openpi
        self.clients: list = []
        probe = connect(url, api_key, use_openpi)
        self.metadata = probe.get_server_metadata()
        self.clients.append(probe)
        self.data_spec = spec_from_metadata(self.metadata)
        self.obs_keys = list(self.metadata["observation"])
        self.n_action_steps = int(self.metadata["n_action_steps"])
        self.attention_log: list = []
        self.latencies_ms: list[float] = []

    def start(self, prompts: list, seeds: list[int]) -> None:
        """Start len(prompts) episodes: rollout i prompted with prompt id ``prompts[i]``, its noise seeded by
        ``seeds[i]`` (the first request of each carries them)."""
        while len(self.clients) < len(prompts):
            self.clients.append(connect(self.url, self.api_key, self.use_openpi))
        self.prompts, self.seeds = list(prompts), [int(s) for s in seeds]
        self.pending: list[list[dict]] = [[] for _ in prompts]
        self.queues: list[list[np.ndarray]] = [[] for _ in prompts]
        self.first = [True] * len(prompts)

    def _request(self, i: int) -> np.ndarray:
        steps = self.pending[i]
        request = {k: np.stack([o[k] for o in steps]) for k in self.obs_keys}
        if self.first[i]:
            request.update(prompt=self.prompts[i], seed=self.seeds[i], reset=True)
        t0 = time.perf_counter()
        reply = self.clients[i].infer(request)
        self.latencies_ms.append(1e3 * (time.perf_counter() - t0))
        self.first[i], self.pending[i] = False, []
        return np.asarray(reply["actions"])[: self.n_action_steps]

    def act_batch(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Next actions (B, A) for observations ``{key: (B, ...)}``; rollouts whose chunk is spent ask the server,
        all at once."""
        n = len(self.prompts)
        for i in range(n):
            self.pending[i].append({k: np.asarray(obs[k][i]) for k in self.obs_keys})
        ask = [i for i in range(n) if not self.queues[i]]
        if ask:
            with ThreadPoolExecutor(len(ask)) as pool:
                for i, chunk in zip(ask, pool.map(self._request, ask), strict=True):
                    self.queues[i] = list(chunk)
        return np.stack([self.queues[i].pop(0) for i in range(n)])

    def close(self) -> None:
        for client in self.clients:
            close(client)
        self.clients = []


# ----------------------------------------------------------------------------------------------- the protocol
def check_same_tasks(meta: dict, store) -> None:
    """The server's prompt library must be the task store the robot scores against: prompts are named by episode."""
    prompts = meta.get("prompts") or {}
    listed = [t["id"] for t in prompts.get("tasks", [])]
    ours = [str(t["id"]) for t in store.tasks[: len(listed)]]
    if prompts.get("episodes") != store.num_episodes or listed != ours:
        raise UserError(
            f"the server offers prompts from {prompts.get('store')!r} ({prompts.get('episodes')} episodes), which is "
            f"not the task store {store.path} ({store.num_episodes} episodes): serve with --prompts {store.path}"
        )


def run_remote(agent: RemoteAgent, benchmark, store, tasks: list[int], protocol, progress: bool = True) -> list:
    """The evaluation protocol's rollouts of `tasks`, each task's rollouts in lockstep against the server; returns
    :class:`bpp.evaluation.protocol.TaskResult` per task."""
    results = []
    bar = tqdm(total=len(tasks) * protocol.rollouts, desc="robot", unit="rollout", disable=not progress)
    for task in tasks:
        plan = protocol.plan(store, task, benchmark)
        agent.start([f"episode:{p['prompt_episode']}" for p in plan], [p["seed"] for p in plan])
        outcome = benchmark.run_rollouts(agent, store, plan, protocol.max_steps, [False] * len(plan))
        results.append(TaskResult(task, str(store.tasks[task]["id"]), rollout_rows(benchmark, plan, outcome)))
        bar.update(len(plan))
    bar.close()
    return results


@dataclass(frozen=True)
class RobotClient:
    """Run ``bpp eval``'s protocol on a benchmark's simulated robots, the policy answering from ``bpp serve``.

    Example (two shells):
      bpp serve runs/bpp_cpu --prompts data/draw/human.zarr
      bpp robot-client --server ws://127.0.0.1:8000 --tasks data/draw/human.zarr --rollouts 4
    """

    tasks: Path
    """The task store (the server must offer prompts from the same store)."""
    server: str = "ws://127.0.0.1:8000"
    api_key: str = ""
    """The server's token, if it requires one (default: $BPP_SERVE_TOKEN)."""
    num_tasks: int = 0
    """Tasks, spread evenly over the store (0: all)."""
    rollouts: int = 4
    seed: int = 0
    max_steps: int = 0
    """Rollout length limit (0: the benchmark's)."""
    prompts: Literal["own", "other-task"] = "own"
    client: Literal["auto", "openpi", "bpp"] = "auto"
    """Which websocket client: openpi's package, bpp's own, or openpi's where installed."""
    out: Path | None = None
    """Write the results as JSON here."""


def robot_client(args: RobotClient) -> dict:
    store = open_store(args.tasks)
    benchmark = get_benchmark(store.benchmark)
    protocol = Protocol(rollouts=args.rollouts, seed=args.seed, prompts=args.prompts)
    protocol = replace(protocol, max_steps=args.max_steps or benchmark.max_steps)
    use_openpi = {"auto": None, "openpi": True, "bpp": False}[args.client]
    agent = RemoteAgent(args.server, args.api_key or os.environ.get("BPP_SERVE_TOKEN") or None, use_openpi)
    client = type(agent.clients[0]).__module__
    try:
        check_same_tasks(agent.metadata, store)
        count = min(args.num_tasks or store.num_tasks, store.num_tasks)
        tasks = np.unique(np.linspace(0, store.num_tasks - 1, count).round().astype(int)).tolist()
        t0 = time.perf_counter()
        results = run_remote(agent, benchmark, store, tasks, protocol)
        seconds = time.perf_counter() - t0
    finally:
        agent.close()
    lat = np.array(agent.latencies_ms)
    meta = {
        "server": args.server,
        "client": client,
        "served": {k: agent.metadata.get(k) for k in ("method", "checkpoint", "train_step", "benchmark")},
        "benchmark": benchmark.name,
        "metric": asdict(benchmark.metric),
        "store": str(store.path),
        "protocol": asdict(protocol),
        "seconds": round(seconds, 1),
        "round_trip_ms": {"p50": float(np.percentile(lat, 50)), "p95": float(np.percentile(lat, 95)), "n": lat.size},
    }
    data = results_json(results, meta, benchmark.metric)
    s = data["summary"]
    print(
        f"{benchmark.metric.name} {benchmark.metric.format(s['score_mean'])} over {s['tasks']} tasks x "
        f"{protocol.rollouts} rollouts ({seconds:.0f} s; round trip p50 {meta['round_trip_ms']['p50']:.1f} ms, "
        f"p95 {meta['round_trip_ms']['p95']:.1f} ms)"
    )
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(data, indent=1, default=float))
        print(f"wrote {args.out}")
    return data


def main(argv: list[str] | None = None) -> None:
    args = tyro.cli(RobotClient, args=argv)
    try:
        robot_client(args)
    except (UserError, OSError) as err:
        print(f"bpp robot-client: {err}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
