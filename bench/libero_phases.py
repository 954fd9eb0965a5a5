"""Phase timing for bench/libero_profile.py: the phases and stages its tables list, :class:`PhaseTimer` (which
charges each moment to the innermost wrapped call running then, in the stage current then), the wrappers it puts on
LIBERO, robosuite, MuJoCo's bindings, our demonstrator, rollouts and policy, and the tables made from it (the
breakdown by phase, cProfile's top functions).

libero_profile.py imports it as a sibling module, as the bench scripts import ``common``.
"""

from __future__ import annotations

import contextlib
import cProfile
import functools
import inspect
import pstats
import time
from collections import Counter, defaultdict

from bpp.evaluation.report import markdown_table

PHYSICS = "physics: mj_step (or mj_step1 + mj_step2)"
FORWARD_LOOP = "physics: mj_forward, robosuite's step loop"
FORWARD_CONTROLLER = "physics: mj_forward, the controller's update"
CONTROLLER = "OSC controller + gripper (robot.control)"
OBSERVABLES = "observations: robosuite's observables"
OBSERVE = "observations: ours (observe, with_derived)"
PREDICATES = "predicates (_check_success, _eval_predicate, holds, GoalOrder)"
GLUE = "env.step glue (robosuite/LIBERO step, reward, _post_action)"
POST_PROCESS = "LIBERO _post_process (object states, site colours)"
PLANNING = "demonstrator: planning (demonstrate_task)"
RECORDING = "demonstrator: recording (Arm.step, Arm.result)"
INFERENCE = "policy: inference (act_batch)"
PROMPT = "policy: prompt encoding (reset_batch)"
CONTEXT = "policy: prompt from the store (task_context)"
GENERATION = "generation bookkeeping (problem text, journal)"
STORE = "writing the store (once per store, not per task)"
ROLLOUT = "rollout loop (run_rollouts, lift tracking)"
GL_CONTEXT = "rendering: GL context (MjRenderContext, SharedRenderer)"
FRAMES = "rendering: frames (render_now, render_states)"
PHASES = [
    PHYSICS,
    FORWARD_LOOP,
    FORWARD_CONTROLLER,
    CONTROLLER,
    OBSERVABLES,
    OBSERVE,
    PREDICATES,
    GLUE,
    POST_PROCESS,
    PLANNING,
    RECORDING,
    INFERENCE,
    PROMPT,
    CONTEXT,
    GENERATION,
    STORE,
    ROLLOUT,
    GL_CONTEXT,
    FRAMES,
]
"""Phases in the order the tables list them (construction and reset phases after them, as they come)."""
STAGES = {
    "construct": "environment construction (make_env, close)",
    "reset": "reset + initial state (env.reset, 10 settle steps, seat)",
    "render": "rendering (goal frame, recorded frames)",
}
"""Stages shown as one row each in the main tables (their phases in a table of their own); the episode stage's
phases get a row each."""
ENV_PHASES = {
    "step": GLUE,
    "_post_action": GLUE,
    "reward": GLUE,
    "_post_process": POST_PROCESS,
    "_update_observables": OBSERVABLES,
    "_get_observations": OBSERVABLES,
    "_check_success": PREDICATES,
    "_eval_predicate": PREDICATES,
    "_load_model": "model: build the MJCF (_load_model)",
    "_initialize_sim": "model: compile the XML (_initialize_sim)",
    "_destroy_sim": "model: free the previous one (_destroy_sim)",
    "_reset_internal": "reset: robot + object placement (_reset_internal)",
}
"""Methods of LIBERO's problem class and its bases (every override: a super() call nests in the same phase)."""


class PhaseTimer:
    """Wall time charged to (stage, phase) cells: each moment goes to the innermost wrapped call running then, in the
    stage current then. Wrapped functions called outside a :meth:`region` run untimed."""

    def __init__(self):
        self.seconds: defaultdict[tuple[str, str], float] = defaultdict(float)
        self.calls: Counter = Counter()
        """(stage, function) -> calls."""
        self.stack: list[str] = []
        self.stage = "episode"
        self.mark = 0.0
        self.wall = 0.0
        self._patches: list[tuple[object, str, object]] = []

    def _charge(self) -> None:
        now = time.perf_counter()
        self.seconds[self.stage, self.stack[-1]] += now - self.mark
        self.mark = now

    @contextlib.contextmanager
    def region(self, phase: str, stage: str = "episode"):
        """Time the block: what no wrapped call takes is charged to `phase`."""
        self.seconds.clear()
        self.calls.clear()
        self.stack, self.stage = [phase], stage
        self.mark = start = time.perf_counter()
        try:
            yield self
        finally:
            self._charge()
            self.stack = []
            self.wall = time.perf_counter() - start

    def replace(self, owner, name: str, function) -> None:
        """Set ``owner.name`` to `function` until :meth:`restore`."""
        self._patches.append((owner, name, inspect.getattr_static(owner, name) if name in vars(owner) else None))
        setattr(owner, name, function)

    def wrap(
        self, owner, name: str, phase, stage: str | None = None, enters: str | None = None, leaves: str | None = None
    ) -> None:
        """Time ``owner.name`` (a module's function or a class's method) as `phase`, or as ``phase(parent phase)``.
        The stage is `stage` during the call (default: unchanged), `enters` from the call on, `leaves` after it."""
        static = inspect.getattr_static(owner, name)
        kind = type(static) if isinstance(static, classmethod | staticmethod) else None
        function = static.__func__ if kind else static
        label = f"{getattr(owner, '__name__', owner)}.{name}"
        timer = self

        @functools.wraps(function)
        def timed(*args, **kwargs):
            if not timer.stack:
                return function(*args, **kwargs)
            timer._charge()
            timer.stage = enters or timer.stage
            before = timer.stage
            timer.stage = stage or timer.stage
            timer.calls[timer.stage, label] += 1
            timer.stack.append(phase(timer.stack[-1]) if callable(phase) else phase)
            try:
                return function(*args, **kwargs)
            finally:
                timer._charge()
                timer.stack.pop()
                timer.stage = leaves or before

        self.replace(owner, name, kind(timed) if kind else timed)

    def restore(self) -> None:
        for owner, name, original in reversed(self._patches):
            if original is None:
                delattr(owner, name)
            else:
                setattr(owner, name, original)
        self._patches.clear()

    def cells(self) -> list[dict]:
        return [
            {"stage": stage, "phase": phase, "seconds": round(s, 4)}
            for (stage, phase), s in sorted(self.seconds.items(), key=lambda item: -item[1])
        ]


def instrument(timer: PhaseTimer, env_class: type, rollout: bool) -> None:
    """Wrap what LIBERO, robosuite, MuJoCo's bindings, our demonstrator or our rollouts and the policy do. In a
    `rollout`, an env made is followed by its reset, and the first action starts the episode."""
    import mujoco
    from libero.libero.envs.env_wrapper import ControlEnv
    from robosuite.robots.single_arm import SingleArm
    from robosuite.utils.binding_utils import MjRenderContext, MjSim

    from bpp.benchmarks.libero import dataset, demonstrator, rollouts, sim
    from bpp.core import prompting
    from bpp.policies.agent import PolicyAgent

    for cls in env_class.__mro__:
        for name, phase in ENV_PHASES.items():
            if name in vars(cls):
                timer.wrap(cls, name, phase)
    timer.wrap(MjSim, "step", PHYSICS)
    for name in ("mj_step1", "mj_step2"):  # sim.make_env's step calls them directly (and LIBERO's placement, mj_step1)
        timer.wrap(mujoco, name, PHYSICS)
    timer.wrap(MjSim, "forward", lambda parent: FORWARD_CONTROLLER if parent == CONTROLLER else FORWARD_LOOP)
    timer.wrap(SingleArm, "control", CONTROLLER)
    timer.wrap(MjRenderContext, "__init__", GL_CONTEXT)
    if hasattr(sim, "SharedRenderer"):  # absent before it existed (--compare's earlier runs)
        timer.wrap(sim.SharedRenderer, "__init__", GL_CONTEXT)
        timer.wrap(sim, "render_assets_digest", "rendering: which shared renderer (the scene's asset digest)")
    timer.wrap(ControlEnv, "__init__", "construction: LIBERO's env (other)")
    timer.wrap(ControlEnv, "step", GLUE)
    timer.wrap(ControlEnv, "reset", "reset: LIBERO's reset (other)")
    timer.wrap(ControlEnv, "close", "construction: close", stage="construct")
    timer.wrap(sim, "make_env", "construction: make_env (other)", stage="construct")
    timer.wrap(
        rollouts, "make_env", "construction: make_env (other)", stage="construct", leaves="reset" if rollout else None
    )
    for module in (sim, demonstrator, rollouts):
        if hasattr(module, "reset_env"):
            timer.wrap(module, "reset_env", "reset: reset_env (other)")
    for module in (sim, demonstrator):
        timer.wrap(module, "seat", "reset: seat (set the state, clear the warm start)")
        timer.wrap(module, "holds", PREDICATES)
    timer.wrap(sim.GoalOrder, "_observe", PREDICATES)
    for module in (sim, rollouts):
        timer.wrap(module, "render_now", FRAMES, stage="render")
    timer.wrap(sim, "render_states", FRAMES, stage="render")
    timer.wrap(demonstrator, "demonstrate_task", PLANNING)
    timer.wrap(dataset, "_write_store", STORE)
    timer.wrap(demonstrator.Arm, "start", "reset: settle steps and Arm.start (other)", stage="reset")
    timer.wrap(demonstrator.Arm, "step", RECORDING)
    timer.wrap(demonstrator.Arm, "result", RECORDING)
    timer.wrap(rollouts, "observe", OBSERVE)
    timer.wrap(PolicyAgent, "act_batch", INFERENCE, enters="episode" if rollout else None)
    timer.wrap(PolicyAgent, "reset_batch", PROMPT)
    timer.wrap(prompting, "task_context", CONTEXT)


@contextlib.contextmanager
def instrumented(env_class: type, rollout: bool):
    timer = PhaseTimer()
    instrument(timer, env_class, rollout)
    try:
        yield timer
    finally:
        timer.restore()


# ------------------------------------------------------------------------------------------------ tables
def breakdown(timer: PhaseTimer, steps: int) -> dict:
    """The main rows (one per stage of :data:`STAGES`, one per phase of the episode), the rows inside construction
    and reset, and every cell."""
    rows: defaultdict[str, float] = defaultdict(float)
    inside: defaultdict[tuple[str, str], float] = defaultdict(float)
    for (stage, phase), seconds in timer.seconds.items():
        rows[STAGES.get(stage, phase)] += seconds
        if stage in STAGES:
            inside[stage, phase] += seconds
    wall = timer.wall

    def order(name: str) -> int:
        return PHASES.index(name) if name in PHASES else len(PHASES)

    stage_rows = [STAGES[s] for s in STAGES if STAGES[s] in rows]
    main = [
        {
            "name": name,
            "seconds": round(rows[name], 4),
            "percent": round(100 * rows[name] / wall, 2),
            "ms_per_step": None if name in stage_rows else round(1e3 * rows[name] / max(steps, 1), 3),
        }
        for name in stage_rows + sorted((n for n in rows if n not in stage_rows), key=lambda n: (order(n), -rows[n]))
    ]
    within = [
        {"stage": stage, "phase": phase, "seconds": round(s, 4), "percent": round(100 * s / wall, 2)}
        for (stage, phase), s in sorted(inside.items(), key=lambda item: (list(STAGES).index(item[0][0]), -item[1]))
    ]
    calls = {f"{stage}: {name}": n for (stage, name), n in sorted(timer.calls.items())}
    return {"wall_s": round(wall, 3), "rows": main, "inside_stages": within, "cells": timer.cells(), "calls": calls}


def print_breakdown(title: str, result: dict, steps: int) -> None:
    print(f"\n## {title}: {result['wall_s']:.2f} s, {steps} episode steps\n")
    rows = [
        (
            r["name"],
            f"{r['seconds']:.3f}",
            f"{r['percent']:.1f}",
            "-" if r["ms_per_step"] is None else f"{r['ms_per_step']:.3f}",
        )
        for r in result["rows"]
    ]
    rows.append(("total", f"{result['wall_s']:.3f}", "100.0", f"{1e3 * result['wall_s'] / max(steps, 1):.3f}"))
    print(markdown_table(["phase", "s", "% of total", "ms per episode step"], rows))
    print(f"### {title}: inside construction, reset and rendering\n")
    rows = [(r["stage"], r["phase"], f"{r['seconds']:.3f}", f"{r['percent']:.1f}") for r in result["inside_stages"]]
    print(markdown_table(["stage", "phase", "s", "% of total"], rows))


def top_functions(profiler: cProfile.Profile, count: int) -> list[dict]:
    """cProfile's `count` functions with the most own time."""
    stats = pstats.Stats(profiler).stats  # type: ignore[attr-defined]
    rows = sorted(stats.items(), key=lambda item: -item[1][2])[:count]
    out = []
    for (path, line, name), (_, calls, own, cumulative, _) in rows:
        short = path.split("site-packages/")[-1].split("/src/")[-1]
        out.append(
            {
                "function": f"{short}:{line}({name})",
                "calls": calls,
                "own_s": round(own, 4),
                "cumulative_s": round(cumulative, 4),
            }
        )
    return out


def print_top(title: str, rows: list[dict]) -> None:
    if rows:
        print(f"\n### cProfile, {title}: top functions by own time\n")
        table = [(r["function"], r["calls"], f"{r['own_s']:.3f}", f"{r['cumulative_s']:.3f}") for r in rows]
        print(markdown_table(["function", "calls", "own s", "cumulative s"], table))
