"""How many of LIBERO-Gen Chain's tasks the scripted demonstrator can demonstrate, judged by LIBERO's predicates.

    python bench/libero_chain_demos.py --view libero_goal_chain_firststep_view --seeds 2
    python bench/libero_chain_demos.py --view libero_goal_chain_selected_view --seeds 2     # the 10 unseen chains

Every task of a view of the published Chain list (tests/data/liberogen_chain_tasks.txt) is written as a LIBERO-Goal
problem (its steps' goals as the goal), loaded in LIBERO, and demonstrated once per seed by the demonstrator's
operators, step after step in one episode. A task's line shows each seed's result (or the error that stopped it);
the last line the total. Needs the `libero` extra. Physics only (no rendering): about 10 s per demonstration here.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from bpp.envs.libero.chain import goal_problem, parse_instruction
from bpp.envs.libero.demonstrator import DemoConfig, demonstrate_steps
from bpp.envs.libero.sim import make_env, problems_folder

TASKS = Path(__file__).resolve().parents[1] / "tests" / "data" / "liberogen_chain_tasks.txt"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--view", default="libero_goal_chain_firststep_view")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--max-steps", type=int, default=1200, help="per demonstration (two steps need more)")
    args = parser.parse_args()
    rows = [line.strip().split("|") for line in TASKS.read_text().splitlines() if line.startswith(args.view + "|")]
    if not rows:
        raise SystemExit(f"no tasks in view {args.view!r} ({TASKS})")
    base = (problems_folder() / "libero_goal" / "turn_on_the_stove.bddl").read_text()  # the scene all ten share
    cfg = DemoConfig(max_steps=args.max_steps)
    successes = 0
    with tempfile.TemporaryDirectory(prefix="libero-chain-") as folder:
        for i, (_, label) in enumerate(rows):
            steps = [(step.operator, step.kwargs) for step in parse_instruction(label)]
            path = Path(folder) / f"task-{i:03d}.bddl"
            path.write_text(goal_problem(label, base))
            t0 = time.perf_counter()
            env = make_env(path)
            results = []
            for seed in range(args.seeds):
                try:
                    results.append(demonstrate_steps(env, steps, seed, cfg).success)
                except ValueError as error:  # an operator the demonstrator does not have yet
                    results.append(f"not demonstrable: {error}")
            env.close()
            successes += sum(r is True for r in results)
            print(f"{label}: {results} ({time.perf_counter() - t0:.0f} s)", flush=True)
    print(f"{successes} of {len(rows) * args.seeds} demonstrations succeeded ({len(rows)} tasks x {args.seeds} seeds)")


if __name__ == "__main__":
    main()
