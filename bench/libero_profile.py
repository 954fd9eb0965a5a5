"""Where one core's time goes in LIBERO-Gen: one task's scripted demonstrations as a generation worker makes them,
and one evaluation rollout of a debug-size policy, each split into phases and set against the bare simulator's step
rate in the same scene.

    OMP_NUM_THREADS=1 MUJOCO_GL=egl python bench/libero_profile.py
    OMP_NUM_THREADS=1 MUJOCO_GL=egl python bench/libero_profile.py --task 5 --demos 1 --max-steps 300
    OMP_NUM_THREADS=1 MUJOCO_GL=egl python bench/libero_profile.py --compare outputs/bench/libero_profile_before.json

1. Demonstrations: :func:`bpp.benchmarks.libero.dataset.generate` of one task (--task, an index into the --preset's
   split; default: Combination's training task 0) with the preset's settings (default `cpu`: a 128 px goal frame,
   no cameras) and --demos demonstrations, in this process: what a generation worker's ``_task_job`` does (problem
   text, ``make_env``, then ``demonstrate_task`` per try, the goal frame, the journal), then the store written.
2. Rollout: a debug-size BPP policy (trained --train-steps steps on that store, one thread) run once as an
   evaluation worker runs a task (``run_prompted``: the prompt encoded, a new env, LIBERO's reset, 10 settle steps,
   then policy and env in lockstep) for --max-steps steps (an untrained policy never ends a rollout early).
3. Anchor: in a new env of the same problem after the same reset, the step rate of env.step with a zero action
   (everything LIBERO does per step), of robosuite's control loop alone (per physics substep: mj_forward, the OSC
   controller, mj_step), of physics alone (mj_forward + mj_step per substep) and of mj_step alone. Then the honest
   anchor of a demonstration: the bare simulator replaying the first stored demonstration's own actions from its first
   state (its scene, controller and contacts; no demonstrator, no rendering), through env.step, through env.step with
   LIBERO's predicates turned off, through robosuite's control loop (mj_forward, controller, mj_step), and as
   mj_step alone with the controller's torques recorded from that loop; each must reproduce the stored states bit for
   bit.

With --compare BEFORE.json (an earlier run's output, e.g. before a change), a table of both runs follows: seconds per
stored demonstration, step rates, and their ratios to every anchor.

Phases are timed by wrapping the functions that do them (MuJoCo's step and forward as robosuite calls them, the
robot's control, the observables, LIBERO's predicates, our demonstrator, the policy, ...): each moment is charged to
the innermost wrapped call running then, within the stage (construct, reset, episode, render) current then, so the
phases add up to the wall time. The wrappers' own cost is measured by repeating a demonstration and the rollout
unwrapped. cProfile's top functions by own time, for one demonstration and one rollout, follow.
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import json
import os
import platform
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from bpp.benchmarks.libero.benchmark import BENCHMARK
from bpp.benchmarks.libero.dataset import PRESETS, LiberoDataConfig, generate, problem_text
from bpp.benchmarks.libero.demonstrator import SETTLE_STEPS
from bpp.checkpoint import Checkpoint
from bpp.data.store import EpisodeStore, stored_with
from bpp.evaluation.protocol import Protocol
from bpp.evaluation.report import markdown_table
from bpp.policies.registry import get_method
from bpp.utils import write_json_atomic
from common import train_run
from libero_phases import GENERATION, GLUE, ROLLOUT, breakdown, instrumented, print_breakdown, print_top, top_functions

TRY = "demonstrator: the same try again, unwrapped (reset, settle, episode)"
ROLLOUT_WHOLE = "rollout, unwrapped (its env built, reset, settle, policy and env in lockstep)"
ROLLOUT_REPLAY = "replay of the rollout: env.step (its actions, settle steps included, from its reset)"


# ------------------------------------------------------------------------------------------------ parts
def demonstrations(cfg: LiberoDataConfig, work: Path) -> tuple[dict, EpisodeStore, object, type]:
    """Part 1: generate --demos demonstrations of one task, timed by phase. Returns the breakdown, the store, the
    task and the class of its LIBERO problem."""
    from bpp.benchmarks.libero import demonstrator

    ((index, task),) = cfg.tasks()
    out = work / "demonstrations.zarr"
    env_class = env_class_of(task, cfg, work)
    tries: list[dict] = []
    with instrumented(env_class, rollout=False) as timer:
        timed = demonstrator.demonstrate_task

        def recorded(env, task, seed, demo_cfg):
            start = time.perf_counter()
            demo = timed(env, task, seed, demo_cfg)
            seconds = time.perf_counter() - start
            tries.append(
                {"seed": seed, "seconds": round(seconds, 3), "steps": len(demo.actions), "success": bool(demo.success)}
            )
            return demo

        timer.replace(demonstrator, "demonstrate_task", recorded)
        with timer.region(GENERATION):
            store = generate(cfg, out, workers=1, overwrite=True, progress=False)
        kept = [t["steps"] for t in tries if t["success"]]
        steps = sum(t["steps"] for t in tries)
        result = breakdown(timer, steps)
    result.update(
        task=task.instruction,
        task_index=index,
        suite=cfg.suite,
        split=cfg.split,
        tries=tries,
        stored_steps=kept,
        episode_steps=steps,
        goal_size=cfg.goal_size,
        cameras=list(cfg.cameras),
    )
    return result, store, task, env_class


def env_class_of(task, cfg, work: Path) -> type:
    """The class of LIBERO's problem behind `task`'s env (read from the problem text, nothing is built)."""
    from libero.libero.envs import TASK_MAPPING
    from libero.libero.envs.bddl_utils import get_problem_info

    path = work / "problem.bddl"
    path.write_text(problem_text(task, cfg.original))
    return TASK_MAPPING[get_problem_info(str(path))["problem_name"]]


def anchor(env, seed: int, steps: int, rounds: int) -> dict:
    """Part 3: step rates in `env` after a reset with `seed` and the settle steps, with a zero action: the fastest
    of `rounds` rounds of `steps` steps per variant (the variants take turns, so a busy moment of a shared machine
    hits all of them), and the median round. Also env.step with the phase timers' wrappers: the difference of the
    medians is their overhead."""
    from bpp.benchmarks.libero.sim import reset_scene

    reset_scene(env, seed)
    zero = np.zeros(7)
    for _ in range(SETTLE_STEPS):
        env.step(zero)
    inner = env.env
    sim = inner.sim
    substeps = int(round(inner.control_timestep / inner.model_timestep))

    def control_loop():  # robosuite's step without the observables, the reward and the observation dictionary
        for i in range(substeps):
            sim.forward()
            inner._pre_action(zero, i == 0)
            sim.step()

    def physics():
        for _ in range(substeps):
            sim.forward()
            sim.step()

    def raw():
        for _ in range(substeps):
            sim.step()

    @contextlib.contextmanager
    def timers_on():
        with instrumented(type(inner), rollout=False) as timer, timer.region(GLUE):
            yield

    variants = {  # name: (one step, what the round runs in)
        "env.step": (lambda: env.step(zero), contextlib.nullcontext),
        "control loop": (control_loop, contextlib.nullcontext),
        "mj_forward + mj_step": (physics, contextlib.nullcontext),
        "mj_step": (raw, contextlib.nullcontext),
        "env.step, phase timers on": (lambda: env.step(zero), timers_on),
    }
    seconds: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(rounds):
        for name, (step, context) in variants.items():
            with context():
                start = time.perf_counter()
                for _ in range(steps):
                    step()
                seconds[name].append((time.perf_counter() - start) / steps)
    rates = {
        name: {
            "ms_per_step": round(1e3 * min(s), 4),
            "steps_per_s": round(1 / min(s), 2),
            "ms_per_step_median": round(1e3 * float(np.median(s)), 4),
            "ms_per_step_per_round": [round(1e3 * x, 4) for x in s],
        }
        for name, s in seconds.items()
    }
    timers = rates.pop("env.step, phase timers on")
    overhead = timers["ms_per_step_median"] - rates["env.step"]["ms_per_step_median"]
    return {
        "substeps": substeps,
        "steps": steps,
        "rounds": rounds,
        "rates": rates,
        "env_step_with_phase_timers": timers,
        "phase_timers_overhead_ms_per_step": round(overhead, 4),
    }


def replay_anchor(env, store: EpisodeStore, episode: int, rounds: int, task=None, demo_cfg=None) -> dict:
    """Part 3, the demonstration's own anchor: stored `episode`'s actions replayed in `env` (made from its problem)
    from its scene (:func:`~bpp.benchmarks.libero.sim.reset_scene` with its seed and fixtures) and first state (seated
    as a replay starts), `rounds` times per variant, the variants taking turns. Each variant's first round also
    collects the states before every action: ``exact`` says whether they are the stored ones bit for bit. With
    `task`, one more variant takes the same turns: the demonstrator's try that made the episode, made again
    unwrapped (its reset and settle steps included), timed per stored step."""
    from bpp.benchmarks.libero.dataset import episode_fixtures
    from bpp.benchmarks.libero.demonstrator import demonstrate_task
    from bpp.benchmarks.libero.sim import reset_scene, seat

    key = "executed_action" if "executed_action" in store.keys else "action"
    steps = store.episode(episode, ["sim_state", key])
    stored, actions = steps["sim_state"], np.asarray(steps[key], dtype=np.float64)
    seed, fixtures = int(store.column("seed")[episode]), episode_fixtures(store, episode)
    inner = env.env
    substeps = int(round(inner.control_timestep / inner.model_timestep))
    torques: list[np.ndarray] = []  # data.ctrl per substep, as the control loop set it

    def env_step(sim, seen):
        for action in actions:
            if seen is not None:
                seen.append(sim.get_state().flatten())
            env.step(action)

    def no_predicates(sim, seen):
        inner._check_success = lambda: False  # LIBERO's step and reward evaluate the goal through it
        try:
            env_step(sim, seen)
        finally:
            del inner._check_success

    def control_loop(sim, seen):  # robosuite's step without observables, reward, predicates and post-processing
        record = seen is not None
        for action in actions:
            if record:
                seen.append(sim.get_state().flatten())
            for i in range(substeps):
                sim.forward()
                inner._pre_action(action, i == 0)
                if record:
                    torques.append(sim.data.ctrl.copy())
                sim.step()

    def physics(sim, seen):
        import mujoco

        model, data = sim.model._model, sim.data._data
        ctrl = iter(torques)
        for _ in actions:
            if seen is not None:
                seen.append(sim.get_state().flatten())
            for _ in range(substeps):
                data.ctrl[:] = next(ctrl)
                mujoco.mj_step(model, data)

    def demonstrator_try(sim, seen):  # the try that made the demonstration, again: reset, settle, episode
        demo = demonstrate_task(env, task, seed, demo_cfg)
        if seen is not None:
            seen.extend(demo.states)

    variants = {
        "replay: env.step": env_step,
        "replay: env.step, no predicates": no_predicates,
        "replay: control loop (mj_forward, controller, mj_step)": control_loop,
        "replay: mj_step alone (the control loop's torques)": physics,
    }
    if task is not None:
        variants[TRY] = demonstrator_try
    seconds: dict[str, list[float]] = {name: [] for name in variants}
    exact: dict[str, bool] = {}
    for r in range(rounds + 1):
        for name, replay in variants.items():
            reset_scene(env, seed, fixtures)
            seat(env, stored[0])
            seen: list | None = [] if r == 0 else None
            start = time.perf_counter()
            replay(inner.sim, seen)
            if r == 0:
                exact[name] = len(seen) == len(stored) and all(map(np.array_equal, seen, stored))
            else:  # the first round collects the states
                seconds[name].append((time.perf_counter() - start) / len(actions))
    return {
        name: {
            "ms_per_step": round(1e3 * min(s), 4),
            "steps_per_s": round(1 / min(s), 2),
            "ms_per_step_median": round(1e3 * float(np.median(s)), 4),
            "ms_per_step_per_round": [round(1e3 * x, 4) for x in s],
            "exact": exact[name],
            "episode": episode,
            "steps": len(actions),
        }
        for name, s in seconds.items()
    }


def rollout_once(agent, store: EpisodeStore, plan, max_steps: int, record) -> int:
    from bpp.core.prompting import run_prompted

    results, _ = run_prompted(agent, BENCHMARK, store, plan, max_steps, record)
    return results[0].steps


def rollout_pair(agent, store: EpisodeStore, plan, max_steps: int, record, rounds: int) -> dict:
    """The rollout against the simulator on the same trajectory: its env's actions (settle steps included) and states
    captured, then `rounds` rounds, taking turns, of the rollout again unwrapped (everything an evaluation worker does
    for it: its env built, reset, settled, policy and env in lockstep) and of its actions replayed through env.step in
    a warm env from the same reset, which must reproduce its states bit for bit. Fastest rounds; the warm env's
    construction is timed too (a rollout builds one)."""
    from bpp.benchmarks.libero import rollouts, sim

    if store.tasks[int(store.column("task_index")[int(plan[0]["target_episode"])])]["info"].get("initial_states"):
        raise SystemExit("rollout_pair replays generated tasks only (LIBERO's own start from its initial states)")
    made = rollouts.make_env
    captured: dict = {"actions": [], "states": []}

    def capturing(problem, **options):
        env = made(problem, **options)
        step = env.step
        captured.update(problem=Path(problem).read_text(), options=options)

        def recording(action):
            captured["actions"].append(np.array(action, dtype=np.float64))
            out = step(action)
            captured["states"].append(env.env.sim.get_state().flatten())
            return out

        env.step = recording
        return env

    rollouts.make_env = capturing
    try:
        steps = rollout_once(agent, store, plan, max_steps, record)
    finally:
        rollouts.make_env = made
    actions, seed = captured["actions"], int(plan[0]["init_seed"])
    seconds: dict[str, list[float]] = {ROLLOUT_WHOLE: [], ROLLOUT_REPLAY: []}
    with tempfile.TemporaryDirectory(prefix="libero-profile-") as folder:
        problem = Path(folder) / "rollout.bddl"
        problem.write_text(captured["problem"])
        start = time.perf_counter()
        env = sim.make_env(problem, **captured["options"])
        construct_s = time.perf_counter() - start
        sim.reset_env(env, seed)
        seen = []
        for action in actions:
            env.step(action)
            seen.append(env.env.sim.get_state().flatten())
        exact = len(seen) == len(captured["states"]) and all(map(np.array_equal, seen, captured["states"]))
        for _ in range(rounds):
            start = time.perf_counter()
            rollout_once(agent, store, plan, max_steps, record)
            seconds[ROLLOUT_WHOLE].append(time.perf_counter() - start)
            start = time.perf_counter()
            sim.reset_env(env, seed)
            for action in actions:
                env.step(action)
            seconds[ROLLOUT_REPLAY].append(time.perf_counter() - start)
        start = time.perf_counter()
        env.close()
        construct_s += time.perf_counter() - start
    return {
        "policy_steps": steps,
        "env_steps": len(actions),
        "replay_exact": exact,
        "construction_s": round(construct_s, 3),
        "rounds": {name: [round(x, 4) for x in s] for name, s in seconds.items()},
        "seconds": {name: round(min(s), 4) for name, s in seconds.items()},
    }


def training_store(store: EpisodeStore, cfg: LiberoDataConfig, work: Path) -> EpisodeStore:
    """`store` (generated with `cfg`) if it holds the two demonstrations training needs, else a store of two
    demonstrations of the same task (generated once into `work`, without a goal frame)."""
    if store.num_episodes >= 2:
        return store
    cfg = replace(cfg, demos_per_task=2, goal_size=0)
    path = work / f"train-task{cfg.task_indices[0]}.zarr"
    return stored_with(path, cfg) or generate(cfg, path, workers=1, overwrite=True, progress=False)


def rollout(args, store: EpisodeStore, cfg: LiberoDataConfig, work: Path, env_class: type) -> dict:
    """Part 2: train a debug BPP on the store (or reuse it), then one rollout of the store's task, timed by phase."""
    model_cfg = get_method("bpp").config("debug", "state", BENCHMARK)
    store = training_store(store, cfg, work)
    run = work / f"bpp-debug-{args.train_steps}-{Path(store.path).stem}"
    start = time.perf_counter()
    train_run("bpp", "debug", "state", store, run, args.train_steps, seed=0, threads=1, model_cfg=model_cfg)
    train_s = time.perf_counter() - start
    from bpp.policies.agent import PolicyAgent

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS") or 1))  # as an evaluation worker does
    checkpoint = Checkpoint.load(run, use_ema=True)
    protocol = Protocol(rollouts=1, seed=args.seed, max_steps=args.max_steps)
    agent = PolicyAgent(checkpoint.build_model(), record_attention=True, **protocol.agent_options())
    plan = protocol.plan(store, 0, BENCHMARK)
    record = [{"none": False, "last": "last", "all": "all"}[args.record]]
    start = time.perf_counter()
    rollout_once(agent, store, plan, args.max_steps, record)  # the first one pays for torch's first calls
    first_s = time.perf_counter() - start
    with instrumented(env_class, rollout=True) as timer:
        with timer.region(ROLLOUT, stage="episode"):
            steps = rollout_once(agent, store, plan, args.max_steps, record)
        result = breakdown(timer, steps)
    start = time.perf_counter()
    plain_steps = rollout_once(agent, store, plan, args.max_steps, record)
    plain_s = time.perf_counter() - start
    top = []
    if args.cprofile_top:
        profiler = cProfile.Profile()
        profiler.runcall(rollout_once, agent, store, plan, args.max_steps, record)
        top = top_functions(profiler, args.cprofile_top)
    pair = rollout_pair(agent, store, plan, args.max_steps, record, args.replay_rounds)
    n_action_steps = agent.n_action_steps
    result.update(
        pair=pair,
        steps=steps,
        plan=plan[0],
        record=args.record,
        train_steps=args.train_steps,
        train_s=round(train_s, 1),
        n_action_steps=n_action_steps,
        inference_calls=-(-steps // n_action_steps),
        first_rollout_s=round(first_s, 3),
        overhead_check={"plain_s": round(plain_s, 3), "plain_steps": plain_steps, "instrumented_s": result["wall_s"]},
        cprofile_top=top,
    )
    return result


def stage_seconds(result: dict, stage: str) -> float:
    return sum(c["seconds"] for c in result["cells"] if c["stage"] == stage)


def rates(demo: dict, roll: dict, bare: dict, warm_construct_s: float, demos_per_task: int) -> dict:
    """Steps per second of the demonstrations (amortised as a generation with the preset's demonstrations per task
    would amortise them) and of the rollout, each with its ratio to every anchor rate."""
    tries, kept = len(demo["tries"]), len(demo["stored_steps"])
    construct = stage_seconds(demo, "construct")
    per_try = (demo["wall_s"] - construct) / tries
    tries_per_demo = tries / max(kept, 1)
    steps_per_demo = float(np.mean(demo["stored_steps"])) if kept else demo["episode_steps"] / tries
    per_demo = warm_construct_s / demos_per_task + tries_per_demo * per_try
    per_demo_cold = construct / demos_per_task + tries_per_demo * per_try
    values = {
        f"demonstrations, amortised: warm construction / {demos_per_task} demos per task, "
        f"{tries_per_demo:.2f} tries per stored demo": steps_per_demo / per_demo,
        "demonstrations, amortised with the process's first (cold) construction": steps_per_demo / per_demo_cold,
        "demonstrations, episode stage only": demo["episode_steps"] / stage_seconds(demo, "episode"),
        "rollout, with its construction and reset": roll["steps"] / roll["wall_s"],
        "rollout, episode stage only": roll["steps"] / stage_seconds(roll, "episode"),
    }
    rows = [
        {
            "name": name,
            "steps_per_s": round(value, 2),
            "ratio_to": {anchor: round(value / r["steps_per_s"], 4) for anchor, r in bare["rates"].items()},
        }
        for name, value in values.items()
    ]
    amortisation = {
        "tries": tries,
        "kept": kept,
        "tries_per_stored_demo": round(tries_per_demo, 3),
        "demos_per_task": demos_per_task,
        "seconds_per_try_after_construction": round(per_try, 3),
        "construction_cold_s": round(construct, 3),
        "construction_warm_s": round(warm_construct_s, 3),
        "steps_per_stored_demo": round(steps_per_demo, 1),
        "seconds_per_stored_demo": round(per_demo, 3),
        "seconds_per_stored_demo_cold_construction": round(per_demo_cold, 3),
    }
    like = paired(demo, roll, bare, warm_construct_s, demos_per_task)
    return {"rows": rows, "amortisation": amortisation, "paired": like}


def paired(demo: dict, roll: dict, bare: dict, warm_construct_s: float, demos_per_task: int) -> list[dict]:
    """Like against like: the demonstrator's try and the rollout, unwrapped and the fastest of rounds taken in turns
    with the simulator stepping the same actions from the same start (so a busy moment of the machine hits both),
    then with what a task or a rollout costs once amortised: a generation worker's warm construction, goal frames
    and bookkeeping over the demonstrations of a task, a rollout's env over its steps."""
    rows = []
    replay = bare["rates"].get("replay: env.step")
    attempt = bare.get("demonstrator_try")
    if replay and attempt:
        sim_s = replay["ms_per_step"] / 1e3 * replay["steps"]
        try_s = attempt["ms_per_step"] / 1e3 * attempt["steps"]
        tries, kept = len(demo["tries"]), max(len(demo["stored_steps"]), 1)
        render_per_demo = stage_seconds(demo, "render") / kept
        per_task = warm_construct_s + sum(c["seconds"] for c in demo["cells"] if c["phase"] == GENERATION)
        rows.append({"name": "a try of the demonstrator (reset, settle, episode)", "seconds": try_s, "sim_s": sim_s})
        for n in sorted({demos_per_task, 50}):
            total = try_s * tries / kept + render_per_demo + per_task / n
            name = f"a stored demonstration, {n} per task (construction, goal frame, bookkeeping amortised)"
            rows.append({"name": name, "seconds": total, "sim_s": sim_s})
    pair = roll.get("pair")
    if pair:
        whole, sim_s = pair["seconds"][ROLLOUT_WHOLE], pair["seconds"][ROLLOUT_REPLAY]
        name = f"a rollout of {pair['env_steps']} env steps, everything"
        rows.append({"name": name, "seconds": whole, "sim_s": sim_s})
        per_step = (whole - pair["construction_s"]) / pair["env_steps"]
        steps = BENCHMARK.max_steps
        rows.append({
            "name": f"a rollout of {steps} env steps (LIBERO-Gen's limit), from the per-step and construction times",
            "seconds": pair["construction_s"] + per_step * steps,
            "sim_s": sim_s / pair["env_steps"] * steps,
        })  # fmt: skip
    for row in rows:
        row["ratio"] = round(row["sim_s"] / row["seconds"], 4)
        row["seconds"], row["sim_s"] = round(row["seconds"], 3), round(row["sim_s"], 3)
    return rows


def machine() -> dict:
    model = ""
    with contextlib.suppress(OSError), open("/proc/cpuinfo") as info:
        model = next((line.split(":", 1)[1].strip() for line in info if "model name" in line), "")
    import mujoco

    return {
        "cpu": model or platform.processor(),
        "cores_visible": os.cpu_count(),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
        "torch_threads": torch.get_num_threads(),
        "mujoco_gl": os.environ.get("MUJOCO_GL"),
        "mujoco": mujoco.__version__,
        "python": platform.python_version(),
        "load_average_at_start": os.getloadavg(),
    }


def anchor_part(args, demo: dict, task, cfg, store: EpisodeStore) -> tuple[dict, float]:
    """Part 3 in a new env of the task (built as generation builds it, warm): the anchor rates (with the replay of
    `store`'s first demonstration), then the last try again unwrapped (the wrappers' overhead; the first try pays for
    first calls) and under cProfile. Returns the anchor and the warm construction's seconds (with the teardown, as
    the demonstrations' construct stage counts it)."""
    from bpp.benchmarks.libero import demonstrator, sim

    last = demo["tries"][-1]
    start = time.perf_counter()
    env = sim.make_env(args.work / "problem.bddl", render=bool(cfg.cameras or cfg.goal_size))
    construct_s = time.perf_counter() - start
    try:
        bare = anchor(env, last["seed"], args.anchor_steps, args.anchor_rounds)
        if store.num_episodes:
            replays = replay_anchor(env, store, 0, args.replay_rounds, task, cfg.demo)
            bare["demonstrator_try"] = replays.pop(TRY)
            bare["rates"].update(replays)
        start = time.perf_counter()
        again = demonstrator.demonstrate_task(env, task, last["seed"], cfg.demo)
        demo["overhead_check"] = {
            "seed": last["seed"],
            "plain_s": round(time.perf_counter() - start, 3),
            "plain_steps": len(again.actions),
            "instrumented_s": last["seconds"],
            "instrumented_steps": last["steps"],
        }
        demo["cprofile_top"] = []
        if args.cprofile_top:
            profiler = cProfile.Profile()
            profiler.runcall(demonstrator.demonstrate_task, env, task, last["seed"], cfg.demo)
            demo["cprofile_top"] = top_functions(profiler, args.cprofile_top)
    finally:
        start = time.perf_counter()
        env.close()
        construct_s += time.perf_counter() - start
    return bare, construct_s


def report(args, info: dict, imports_s: float, bare: dict, demo: dict, roll: dict, summary: dict) -> None:
    print(f"\n# LIBERO-Gen on one core: {info['cpu']}, OMP_NUM_THREADS={info['omp_num_threads']}\n")
    print(
        f"Task {demo['task_index']} of {demo['suite']} {demo['split']}: {demo['task']!r}; the `{args.preset}` "
        f"preset's settings (goal frame {demo['goal_size']} px, cameras {demo['cameras'] or 'none'}); imports "
        f"{imports_s:.1f} s (once per process, not counted below)."
    )
    print(
        f"\n## Anchor: zero action after reset + settle, {bare['steps']} steps, {bare['substeps']} physics substeps "
        "per control step\n"
    )
    physics_ms = bare["rates"]["mj_step"]["ms_per_step"]
    zero = {name: r for name, r in bare["rates"].items() if not name.startswith("replay")}
    replayed = {name: r for name, r in bare["rates"].items() if name.startswith("replay")}
    rows = [
        (name, f"{r['ms_per_step']:.3f}", f"{r['ms_per_step_median']:.3f}", f"{r['steps_per_s']:.1f}",
         f"{r['ms_per_step'] / physics_ms:.2f}")
        for name, r in zero.items()
    ]  # fmt: skip
    header = ["per control step", "ms (fastest round)", "ms (median round)", "steps/s (fastest)", "x mj_step alone"]
    print(markdown_table(header, rows))
    if replayed:
        first = next(iter(replayed.values()))
        print(
            f"## Anchor: stored demonstration {first['episode']} replayed ({first['steps']} steps: its actions from "
            "its first state, in its scene)\n"
        )
        rows = [
            (name, f"{r['ms_per_step']:.3f}", f"{r['ms_per_step_median']:.3f}", f"{r['steps_per_s']:.1f}",
             "yes" if r["exact"] else "NO")
            for name, r in replayed.items()
        ]  # fmt: skip
        print(markdown_table(["per control step", *header[1:4], "states bit for bit"], rows))
    print(
        f"Ratios below are to the fastest rounds. The phase timers' wrappers add "
        f"{bare['phase_timers_overhead_ms_per_step']:.3f} ms to an env.step (medians; "
        f"{bare['env_step_with_phase_timers']['ms_per_step_median']:.3f} ms with them)."
    )
    print_breakdown("Demonstrations (generation of one task)", demo, demo["episode_steps"])
    tries = ", ".join(
        f"seed {t['seed']}: {t['steps']} steps, {'ok' if t['success'] else 'failed'}, {t['seconds']:.2f} s"
        for t in demo["tries"]
    )
    check = demo["overhead_check"]
    print(
        f"Tries (reset + episode): {tries}. Wrappers' overhead: the last try took {check['instrumented_s']:.2f} s "
        f"wrapped ({check['instrumented_steps']} steps), {check['plain_s']:.2f} s unwrapped ({check['plain_steps']} "
        "steps)."
    )
    print_breakdown(f"Rollout (debug BPP, {roll['n_action_steps']} actions per inference)", roll, roll["steps"])
    check = roll["overhead_check"]
    print(
        f"Wrappers' overhead: {roll['wall_s']:.2f} s wrapped, {check['plain_s']:.2f} s unwrapped "
        f"({check['plain_steps']} steps); the first rollout in the process took {roll['first_rollout_s']:.2f} s. "
        f"Training the debug policy: {roll['train_s']:.0f} s (reused when already trained)."
    )
    a = summary["amortisation"]
    print(
        f"\n## Rates and ratios to the anchor\n\nAmortised: construction {a['construction_warm_s']:.2f} s warm "
        f"({a['construction_cold_s']:.2f} s cold) per task of {a['demos_per_task']} stored demos, "
        f"{a['seconds_per_try_after_construction']:.2f} s per try after it, {a['tries_per_stored_demo']:.2f} tries per "
        f"stored demo of {a['steps_per_stored_demo']:.0f} steps: {a['seconds_per_stored_demo']:.2f} s per stored demo."
        "\n"
    )
    header = ["steps/s of", "steps/s", *(f"/ {name}" for name in bare["rates"])]
    rows = [
        (r["name"], f"{r['steps_per_s']:.1f}", *(f"{v:.3f}" for v in r["ratio_to"].values())) for r in summary["rows"]
    ]
    print(markdown_table(header, rows))
    if summary.get("paired"):
        attempt, pair = bare.get("demonstrator_try"), roll.get("pair")
        notes = []
        if attempt:
            notes.append(f"the try reproduces the stored states bit for bit: {'yes' if attempt['exact'] else 'NO'}")
        if pair:
            notes.append(
                f"the rollout's replay reproduces its states bit for bit: {'yes' if pair['replay_exact'] else 'NO'}; "
                f"its env's construction (warm) {pair['construction_s']:.2f} s"
            )
        print(
            "\n## Like against like: the simulator stepping the same actions from the same start\n\n"
            "Fastest of rounds taken in turns, unwrapped; " + "; ".join(notes) + ".\n"
        )
        rows = [(r["name"], f"{r['seconds']:.2f}", f"{r['sim_s']:.2f}", f"{r['ratio']:.2f}") for r in summary["paired"]]
        print(markdown_table(["", "s", "simulator s (env.step)", "simulator rate / ours"], rows))
    print_top("one demonstration", demo["cprofile_top"])
    print_top("one rollout", roll["cprofile_top"])


def compare(before: dict, after: dict) -> None:
    """Print `before` (an earlier run's output) against `after`: seconds per stored demonstration, the anchors, the
    step rates and their ratios to every anchor both runs have."""
    b, a = before["rates"], after["rates"]
    print("\n## Before / after\n")
    keys = [
        ("seconds_per_stored_demo", "s per stored demo (warm construction amortised)"),
        ("seconds_per_stored_demo_cold_construction", "s per stored demo (cold construction amortised)"),
        ("seconds_per_try_after_construction", "s per try after construction"),
        ("construction_warm_s", "construction, warm (s)"),
        ("steps_per_stored_demo", "steps per stored demo"),
    ]
    rows = [
        (label, f"{b['amortisation'][k]:.3f}", f"{a['amortisation'][k]:.3f}",
         f"{a['amortisation'][k] / b['amortisation'][k]:.3f}")
        for k, label in keys
    ]  # fmt: skip
    for part in ("demonstrations", "rollout"):
        for stage in ("reset", "episode"):
            old, new = stage_seconds(before[part], stage), stage_seconds(after[part], stage)
            if old and new:
                rows.append((f"{part}: {stage} stage (s)", f"{old:.3f}", f"{new:.3f}", f"{new / old:.3f}"))
    anchors = [name for name in a["rows"][0]["ratio_to"] if name in b["rows"][0]["ratio_to"]]
    for name in anchors:
        old, new = before["anchor"]["rates"][name]["ms_per_step"], after["anchor"]["rates"][name]["ms_per_step"]
        rows.append((f"anchor ms/step: {name}", f"{old:.3f}", f"{new:.3f}", f"{new / old:.3f}"))
    rows += [
        (f"steps/s: {old['name']}", f"{old['steps_per_s']:.1f}", f"{new['steps_per_s']:.1f}",
         f"{new['steps_per_s'] / old['steps_per_s']:.3f}")
        for old, new in zip(b["rows"], a["rows"], strict=True)
    ]  # fmt: skip
    print(markdown_table(["", "before", "after", "after / before"], rows))
    print("Rates as a fraction of each anchor's rate (before -> after):\n")
    rows = [
        (old["name"], *(f"{old['ratio_to'][n]:.3f} -> {new['ratio_to'][n]:.3f}" for n in anchors))
        for old, new in zip(b["rows"], a["rows"], strict=True)
    ]
    print(markdown_table(["steps/s of", *(f"/ {n}" for n in anchors)], rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    combination = [name for name, cfg in PRESETS.items() if cfg.suite == "combination"]
    parser.add_argument(
        "--preset",
        choices=combination,
        default="cpu",
        help="data preset whose settings the demonstrations use (goal frame, cameras, tries); its demos_per_task "
        "amortises the construction",
    )
    parser.add_argument("--task", type=int, default=0, help="index of the task in the preset's split")
    parser.add_argument("--demos", type=int, default=2, help="demonstrations to make (1-2 keep it short)")
    parser.add_argument("--max-steps", type=int, default=200, help="rollout length")
    parser.add_argument(
        "--record",
        choices=["none", "last", "all"],
        default="none",
        help="frames the rollout records (an evaluation records rollout 0 of each task)",
    )
    parser.add_argument("--train-steps", type=int, default=10, help="training steps of the debug policy")
    parser.add_argument("--anchor-steps", type=int, default=20, help="steps per round of each anchor rate")
    parser.add_argument("--anchor-rounds", type=int, default=12, help="rounds of each anchor rate (the fastest counts)")
    parser.add_argument("--replay-rounds", type=int, default=8, help="rounds of each replay anchor, taken in turns")
    parser.add_argument("--compare", type=Path, help="an earlier run's JSON output: print both runs side by side")
    parser.add_argument("--cprofile-top", type=int, default=25, help="functions listed per cProfile pass (0: none)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", type=Path, default=Path("runs/libero_profile"), help="the store and the policy")
    parser.add_argument("--out", type=Path, default=Path("outputs/bench/libero_profile.json"))
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    began = time.perf_counter()
    info = machine()
    cfg = PRESETS[args.preset]

    from bpp.benchmarks.libero import sim

    start = time.perf_counter()
    sim._libero()
    import libero.libero.envs  # noqa: F401 - the env classes, imported by the first make_env otherwise

    # make_env replaces robosuite's env step on first use: done now, the phase timers wrap (and then put back) the
    # step in use, not robosuite's, which would stay in place once they restore it.
    if hasattr(sim, "_install_fast_step"):  # absent before it existed (--compare's earlier runs)
        sim._install_fast_step()
    imports_s = time.perf_counter() - start
    print(f"[libero_profile] imports {imports_s:.1f} s; part 1: {args.demos} demonstrations", flush=True)
    demo_cfg = replace(cfg, task_indices=(args.task,), num_tasks=0, demos_per_task=args.demos)
    demo, store, task, env_class = demonstrations(demo_cfg, args.work)
    print("[libero_profile] part 3: anchor; a demonstration unwrapped and under cProfile", flush=True)
    bare, warm_construct_s = anchor_part(args, demo, task, cfg, store)
    print(f"[libero_profile] part 2: a rollout of {args.max_steps} steps", flush=True)
    roll = rollout(args, store, demo_cfg, args.work, env_class)
    summary = rates(demo, roll, bare, warm_construct_s, cfg.demos_per_task)
    report(args, info, imports_s, bare, demo, roll, summary)
    seconds = time.perf_counter() - began
    info["load_average_at_end"] = os.getloadavg()
    data = {"command": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}, "machine": info}
    data |= {"imports_s": round(imports_s, 3), "anchor": bare, "demonstrations": demo, "rollout": roll}
    data |= {"rates": summary, "seconds": round(seconds, 1)}
    write_json_atomic(args.out, data)
    if args.compare:
        compare(json.loads(args.compare.read_text()), data)
    print(f"\n[libero_profile] {seconds:.0f} s; wrote {args.out}")


if __name__ == "__main__":
    main()
