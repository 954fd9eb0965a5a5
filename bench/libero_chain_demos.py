"""How many of LIBERO-Gen Chain's tasks the scripted demonstrator can demonstrate, judged by LIBERO's predicates.

    python bench/libero_chain_demos.py --view first_step --seeds 2
    python bench/libero_chain_demos.py --view unseen_chains --seeds 2     # the 10 held-out chains
    python bench/libero_chain_demos.py --view all --match "middle drawer"  # every task that names it

Every task of a view of the Chain suite (`bpp.benchmarks.libero.chain`: first_step, second_step, seen_chains,
unseen_chains) is written as its LIBERO-Goal problem (a second-step task's start state in its ``:init``), loaded in
LIBERO, and demonstrated once per seed by the demonstrator's operators, step after step in one episode. A task's
line shows each seed's result; the last line the total. Needs the `libero` extra.
Physics only (no rendering): about 10 s per demonstration here. `bpp libero generate --preset chain-cpu` is the
same per task, stored.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from bpp.benchmarks.libero.chain import VIEWS, chain
from bpp.benchmarks.libero.dataset import problem_text
from bpp.benchmarks.libero.demonstrator import DemoConfig, demonstrate_task
from bpp.benchmarks.libero.sim import make_env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--view", default="first_step", choices=[*sorted(VIEWS), "all"])
    parser.add_argument("--match", default="", help="only the tasks whose label contains this text")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--max-steps", type=int, default=1200, help="per demonstration (two steps need more)")
    args = parser.parse_args()
    suite = chain()
    tasks = [
        t
        for t in (*suite.train, *suite.test)
        if args.view in ("all", t.view) and args.match in f"{t.label} {t.start or ''}"
    ]
    cfg = DemoConfig(max_steps=args.max_steps)
    successes = 0
    with tempfile.TemporaryDirectory(prefix="libero-chain-") as folder:
        for i, task in enumerate(tasks):
            path = Path(folder) / f"task-{i:03d}.bddl"
            path.write_text(problem_text(task))
            t0 = time.perf_counter()
            env = make_env(path)
            results = [demonstrate_task(env, task, seed, cfg).success for seed in range(args.seeds)]
            env.close()
            successes += sum(results)
            start = f" (from: {task.start})" if task.start else ""
            print(f"{task.label}{start}: {results} ({time.perf_counter() - t0:.0f} s)", flush=True)
    print(
        f"{successes} of {len(tasks) * args.seeds} demonstrations succeeded ({len(tasks)} tasks x {args.seeds} seeds)"
    )


if __name__ == "__main__":
    main()
