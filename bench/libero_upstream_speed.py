"""LIBERO-Gen's simulation against upstream LIBERO's own environment, side by side on one core: the same scene,
controller and demonstrations, simulated by LIBERO's code as its own scripts use it and by bpp's.

    OMP_NUM_THREADS=1 python bench/libero_upstream_speed.py                          # Combination task 0, 3 demos
    OMP_NUM_THREADS=1 python bench/libero_upstream_speed.py --demos 150 --goal-size 0 --episodes $(seq 0 29)
    OMP_NUM_THREADS=1 python bench/libero_upstream_speed.py --store data/libero/drawer.zarr --episodes 0 1 2 --rounds 5

Each side runs in a process of its own (bpp replaces robosuite's step process-wide), the two taking turns round by
round, so that a busy moment of a shared machine hits both:

- upstream: LIBERO's ``ControlEnv`` (physics only, as bpp's `cpu` preset simulates), built as LIBERO builds it; per
  demonstration ``env.seed(seed)`` and ``env.reset()`` (LIBERO's reset: the model rebuilt and compiled), 10 steps
  with a zero action (LIBERO's evaluation waits as many), ``set_init_state`` with the first stored state, then the
  demonstration's actions through robosuite's step. LIBERO's reset places the fixtures for the seed as the
  demonstration's reset did; the constants MuJoCo derives from their poses stay LIBERO's own.
- bpp: ``make_env``, then per demonstration its scene (``reset_scene``: the soft reset, the stored fixtures), the
  same 10 steps, ``seat`` with the first stored state, the same actions through bpp's step. Its replays must pass
  through the stored states bit for bit.

Printed per side: building an env (a process's first, with its imports, and another), a reset, a step, a demonstration's
replay, and whether each replay reached its goal; then what they make per hour: rollouts of LIBERO-Gen's 550-step limit
(another env built, reset, 10 + 550 steps; no policy on either side) and demonstrations, bpp's as this store was
generated (demonstrator, failed tries and writing included) against upstream's replay of the same demonstrations, the
least any generator running on upstream's environment would spend (which renders nothing: a store generated with goal
frames, the `cpu` preset's default, pays for drawing them and upstream's side does not; ``--goal-size 0`` generates a
state-only store, as a ladder of BPP alone needs). Needs the `libero` extra; LIBERO's package as bpp installs it (its
checks: docs/installation.md).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bpp.benchmarks.libero import sim
from bpp.benchmarks.libero.dataset import PRESETS, episode_fixtures, generate
from bpp.benchmarks.libero.rollouts import task_problem
from bpp.data.store import EpisodeStore

SETTLE = 10
"""Zero-action steps after a reset, on both sides (bpp's demonstrator and LIBERO's evaluation both wait this many)."""
LIMIT = 550
"""LIBERO-Gen's step limit for a rollout."""


def _upstream_env(problem: Path):
    """LIBERO's physics-only env, as LIBERO builds it, in a process where bpp's step was never installed."""
    # LIBERO: the libero extra
    from libero.libero.envs.env_wrapper import ControlEnv

    assert sim._ROBOSUITE_STEP is None, "bpp's step is installed in the upstream side's process"
    return ControlEnv(
        bddl_file_name=str(problem),
        horizon=1000,
        has_renderer=False,
        has_offscreen_renderer=False,
        use_camera_obs=False,
    )


def run_side(side: str, problem: Path, episodes: Path) -> dict:
    """One side's timings in this process: `episodes` holds seed, fixtures, states and actions per demonstration."""
    data = np.load(episodes, allow_pickle=False)
    names = [str(n) for n in data["fixture_names"]]
    builds = []
    for _ in range(2):  # the first pays the process's imports and caches, the second is what a worker pays again
        start = time.perf_counter()
        env = _upstream_env(problem) if side == "upstream" else sim.make_env(problem)
        builds.append(time.perf_counter() - start)
        if len(builds) == 1:
            env.close()
    zero = np.zeros(7)
    rows = []
    for i in range(int(data["count"])):
        seed, states, actions = int(data[f"seed_{i}"]), data[f"states_{i}"], data[f"actions_{i}"]
        t0 = time.perf_counter()
        if side == "upstream":  # LIBERO's reset rebuilds and compiles the model
            env.seed(seed)
            env.reset()
        else:
            sim.reset_scene(env, seed, (names, data[f"fixtures_{i}"]))
        t1 = time.perf_counter()
        for _ in range(SETTLE):
            env.step(zero)
        if side == "upstream":
            env.set_init_state(states[0])
        else:
            sim.seat(env, states[0])
        exact = True
        for t, action in enumerate(actions):
            exact = exact and np.array_equal(env.env.sim.get_state().flatten(), states[t])
            env.step(action)
        t2 = time.perf_counter()
        steps = SETTLE + len(actions)
        rows.append(
            {
                "reset_s": t1 - t0,
                "step_ms": 1e3 * (t2 - t1) / steps,
                "replay_s": t2 - t0,
                "steps": steps,
                "success": bool(env.env._check_success()),
                "exact": bool(exact),
            }
        )
    env.close()
    if side == "upstream":
        assert sim._ROBOSUITE_STEP is None  # robosuite's own step ran throughout
    return {"side": side, "first_build_s": builds[0], "build_s": builds[1], "episodes": rows}


def export_episodes(store_path: Path, chosen: list[int], folder: Path) -> tuple[Path, Path]:
    """The chosen demonstrations (one task) as arrays for the sides, and the task's problem file."""
    store = EpisodeStore(store_path)
    tasks = store.column("task_index")
    if len({int(tasks[e]) for e in chosen}) != 1:
        raise SystemExit("--episodes must be demonstrations of one task (one env per side)")
    problem = folder / "problem.bddl"
    problem.write_text(task_problem(store, chosen[0]))
    key = "executed_action" if "executed_action" in store.keys else "action"
    arrays: dict[str, np.ndarray] = {"count": np.array(len(chosen))}
    for i, episode in enumerate(chosen):
        names, poses = episode_fixtures(store, episode)
        steps = store.episode(episode, ["sim_state", key])
        arrays["fixture_names"] = np.array(names)
        arrays[f"seed_{i}"] = np.array(int(store.column("seed")[episode]))
        arrays[f"fixtures_{i}"] = poses
        arrays[f"states_{i}"] = steps["sim_state"]
        arrays[f"actions_{i}"] = steps[key]
    path = folder / "episodes.npz"
    np.savez(path, **arrays)
    return problem, path


def generated_store(folder: Path, demos: int, goal_size: int) -> tuple[Path, float]:
    """Combination's training task 0, `demos` demonstrations, generated here on one core (timed); `goal_size`: the
    side of each demonstration's goal frame (0: none, a state-only store)."""
    out = folder / "store.zarr"
    cfg = replace(PRESETS["cpu"], task_indices=(0,), demos_per_task=demos, goal_size=goal_size)
    start = time.perf_counter()
    generate(cfg, out, workers=1, progress=False)
    return out, time.perf_counter() - start


def medians(results: list[dict]) -> dict:
    """Medians over rounds of each side's per-demonstration means."""
    keys = ("reset_s", "step_ms", "replay_s")
    rounds = [{k: statistics.mean(e[k] for e in res["episodes"]) for k in keys} for res in results]
    return {k: statistics.median(r[k] for r in rounds) for k in keys} | {
        k: statistics.median(res[k] for res in results) for k in ("first_build_s", "build_s")
    }


def sides(args, problem: Path, arrays: Path) -> dict[str, list[dict]]:
    """Each side's results per round, the two taking turns (each in a new process)."""
    runs: dict[str, list[dict]] = {"upstream": [], "bpp": []}
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    for r in range(args.rounds):
        for side in ("upstream", "bpp") if r % 2 == 0 else ("bpp", "upstream"):
            command = [sys.executable, __file__, "--side", side, "--problem", str(problem), "--arrays", str(arrays)]
            done = subprocess.run(command, capture_output=True, text=True, env=env, check=False)
            if done.returncode:
                raise SystemExit(f"the {side} side failed:\n{done.stderr[-3000:]}")
            runs[side].append(json.loads(done.stdout.strip().splitlines()[-1]))
            print(f"round {r + 1}: {side} done", flush=True)
    return runs


def report(result: dict) -> None:
    runs, median = result["runs"], result["median"]
    print(f"\n{result['store']}: {len(result['episodes'])} demonstrations replayed, {result['rounds']} rounds, medians")
    columns = ["first env (s)", "another env (s)", "a reset (s)", "a step (ms)", "a replay (s)", "reached goal"]
    print("| side | " + " | ".join(columns) + " | bit for bit |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for side in ("upstream", "bpp"):
        m, episodes = median[side], [e for res in runs[side] for e in res["episodes"]]
        reached = f"{sum(e['success'] for e in episodes)} / {len(episodes)}"
        exact = f"{sum(e['exact'] for e in episodes)} / {len(episodes)}"
        cells = f"{m['first_build_s']:.2f} | {m['build_s']:.2f} | {m['reset_s']:.3f} | {m['step_ms']:.2f}"
        cells += f" | {m['replay_s']:.2f}"
        print(f"| {side} | {cells} | {reached} | {exact} |")
    per_hour = result["rollouts_per_hour"]
    ratio = per_hour["bpp"] / per_hour["upstream"]
    print(f"\nrollouts of {LIMIT} steps per hour: upstream {per_hour['upstream']:.0f}, ", end="")
    print(f"bpp {per_hour['bpp']:.0f} ({ratio:.2f}x)")
    if "demonstrations_per_hour" in result:
        d = result["demonstrations_per_hour"]
        ratio = d["bpp generating"] / d["upstream replaying"]
        g = result["generation"]
        print(f"demonstrations per hour: bpp generating {d['bpp generating']:.0f} ", end="")
        print(f"({g['demonstrations']} in {g['seconds']:.1f} s), ", end="")
        print(f"upstream replaying them {d['upstream replaying']:.0f} ({ratio:.2f}x)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--store", type=Path, help="a LIBERO-Gen store (default: generate task 0 here, timed)")
    parser.add_argument("--demos", type=int, default=3, help="demonstrations to generate without --store")
    parser.add_argument(
        "--episodes",
        type=int,
        nargs="+",
        help="demonstrations replayed, of one task (default: all the store's, if it holds one task); with a store "
        "generated here, a sample of it times the replays and its rate per hour counts all its demonstrations",
    )
    parser.add_argument(
        "--goal-size",
        type=int,
        default=PRESETS["cpu"].goal_size,
        help="without --store: the side (px) of each demonstration's goal frame, rendered for Goal-Image's prompts "
        "(default: the cpu preset's; 0: a state-only store, which builds its env without textures and renders nothing)",
    )
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("outputs/bench/libero_upstream_speed.json"))
    parser.add_argument("--side", choices=["upstream", "bpp"], help=argparse.SUPPRESS)
    parser.add_argument("--problem", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--arrays", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.side:
        print(json.dumps(run_side(args.side, args.problem, args.arrays)))
        return
    with tempfile.TemporaryDirectory(prefix="libero-upstream-") as tmp:
        generation_s, store = None, args.store
        if store is None:
            store, generation_s = generated_store(Path(tmp), args.demos, args.goal_size)
        stored = EpisodeStore(store).num_episodes
        chosen = args.episodes or list(range(stored))
        runs = sides(args, *export_episodes(store, chosen, Path(tmp)))
    median = {side: medians(res) for side, res in runs.items()}
    frames = f"goal frames of {args.goal_size} px" if args.goal_size else "state only (no goal frames)"
    rollout_s = {s: m["build_s"] + m["reset_s"] + (SETTLE + LIMIT) * m["step_ms"] / 1e3 for s, m in median.items()}
    result = {
        "store": str(args.store or f"generated here: Combination task 0, {args.demos} demonstrations, {frames}"),
        "episodes": chosen,
        "rounds": args.rounds,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "median": median,
        "rollouts_per_hour": {s: 3600 / v for s, v in rollout_s.items()},
        "runs": runs,
    }
    if generation_s is not None:  # per demonstration of the store, upstream's first env shared by as many
        up = median["upstream"]
        result["demonstrations_per_hour"] = {
            "bpp generating": 3600 * stored / generation_s,
            "upstream replaying": 3600 / (up["replay_s"] + up["first_build_s"] / stored),
        }
        result["generation"] = {"demonstrations": stored, "seconds": generation_s}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    report(result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
