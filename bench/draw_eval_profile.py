"""Where a DrawAnything evaluation's time goes, and how close its policy runs to the machine's limit.

    python bench/draw_eval_profile.py runs/demo-bpp                       # 8 unseen drawings x 8 rollouts
    python bench/draw_eval_profile.py RUN --num-tasks 16 --tasks-per-batch 16

In one process on `--threads` torch threads (default 1): `bpp eval`'s protocol (one worker, batches of
`--tasks-per-batch` tasks, no videos), timing the policy's calls (``PolicyAgent.act_batch``), the environment's steps
(``DrawEnv.step``: the pen's physics, its ink and the metric's bookkeeping) and, apart, the scoring at each episode's
end (``ChamferTracker.score`` and ``best``). Then the same rollouts again with torch's FLOP counter around the
policy's calls, and one core's fp32 matrix-product rate in the same run: the policy's GFLOP/s against that peak,
which bounds what a faster policy on this CPU can gain; the rest of the time is the environment's.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

from bpp.benchmarks.draw.env import DrawEnv
from bpp.drawing.metric import ChamferTracker
from bpp.evaluation.evaluate import evaluate
from bpp.evaluation.protocol import Protocol
from bpp.policies.agent import PolicyAgent
from common import add_eval_arguments, evaluated_tasks, matmul_peak


@contextmanager
def timed(owner, name: str, seconds: dict, key: str):
    """Add the time spent in ``owner.name`` to ``seconds[key]`` while the context is open."""
    original = getattr(owner, name)

    def wrapper(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return original(*args, **kwargs)
        finally:
            seconds[key] += time.perf_counter() - t0

    setattr(owner, name, wrapper)
    try:
        yield
    finally:
        setattr(owner, name, original)


@contextmanager
def counted(flops: list):
    """Count the FLOPs of every ``PolicyAgent.act_batch`` call into ``flops[0]`` while the context is open."""
    original = PolicyAgent.act_batch

    def wrapper(self, *args, **kwargs):
        with FlopCounterMode(display=False) as counter:
            result = original(self, *args, **kwargs)
        flops[0] += counter.get_total_flops()
        return result

    PolicyAgent.act_batch = wrapper
    try:
        yield
    finally:
        PolicyAgent.act_batch = original


def run(ckpt, task_set, tasks, protocol, out: Path) -> float:
    t0 = time.perf_counter()
    evaluate(ckpt, task_set, tasks, out, protocol, workers=1, videos=0, progress=False, reuse=False)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_eval_arguments(parser, num_tasks=8, rollouts=8)
    parser.add_argument("--tasks-per-batch", type=int, default=8)
    args = parser.parse_args()
    ckpt, _, task_set, tasks = evaluated_tasks(args)
    protocol = Protocol(rollouts=args.rollouts, tasks_per_batch=args.tasks_per_batch)
    seconds = dict.fromkeys(("policy", "env", "end scoring"), 0.0)
    with tempfile.TemporaryDirectory(prefix="draw-eval-profile-") as tmp:
        with (
            timed(PolicyAgent, "act_batch", seconds, "policy"),
            timed(DrawEnv, "step", seconds, "env"),
            timed(ChamferTracker, "best", seconds, "end scoring"),
        ):
            wall = run(ckpt, task_set, tasks, protocol, Path(tmp) / "timed")
        flops = [0.0]
        with counted(flops):
            run(ckpt, task_set, tasks, protocol, Path(tmp) / "counted")
    peak = matmul_peak(torch.float32, args.threads)
    rollouts = len(tasks) * args.rollouts
    policy_rate = flops[0] / seconds["policy"] / 1e9
    rest = wall - seconds["policy"] - seconds["env"]
    print(f"{rollouts} rollouts in {wall:.1f} s ({rollouts / wall:.2f} a second) on {args.threads} thread(s)")
    print(f"policy {seconds['policy']:.1f} s ({seconds['policy'] / wall:.0%}), env steps {seconds['env']:.1f} s "
          f"({seconds['env'] / wall:.0%}; of it, the best score at the end {seconds['end scoring']:.2f} s), "
          f"the rest {rest:.1f} s ({rest / wall:.0%})")  # fmt: skip
    print(f"the policy: {flops[0] / 1e9:.1f} GFLOP, {policy_rate:.1f} GFLOP/s, {policy_rate / peak:.0%} of one core's "
          f"fp32 matrix-product rate ({peak:.1f} GFLOP/s x {args.threads} thread(s), measured now)")  # fmt: skip
    print(
        f"at the peak the policy would take {flops[0] / 1e9 / peak:.1f} s: the evaluation at most "
        f"{wall / (wall - seconds['policy'] + flops[0] / 1e9 / peak):.2f}x faster with the environment as it is"
    )


if __name__ == "__main__":
    main()
