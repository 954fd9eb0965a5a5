"""LIBERO-Gen rollouts: a policy, already given each rollout's task context, acts in LIBERO from a new initial
state; LIBERO's own goal predicates score it (the goal holding at any step ends the rollout), as in the paper's
protocol. A Chain task succeeds only if its steps were done in their order (:class:`~bpp.benchmarks.libero.sim.
GoalOrder`): three unseen chains have the same final goal as a training chain with its two steps the other way round.
Its rollouts also record the final goal alone (``final_goal``, order ignored) and whether the first step was done
(``first_step``); LIBERO's own tasks keep LIBERO's success, which ignores the order. Each rollout also records how far
it got: whether it lifted an object its goal moves (``lifted``) and whether it lifted any other object
(``lifted_other``), by at least :data:`LIFT` above where the object started. With two identical bowls (Combination),
picking the right one is what the prompt has to convey.

Rollouts step in lockstep through one batched agent; each has its own env (physics only unless the policy
observes cameras or a video is recorded). Camera observations are rendered from the simulator state after each
step, upright, the same way training frames are rendered from stored states.
"""

from __future__ import annotations

import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from bpp.benchmarks.libero.bddl import objects, parse, section
from bpp.benchmarks.libero.dataset import ABSOLUTE_KEY, DERIVED_KEYS
from bpp.benchmarks.libero.demonstrator import SETTLE_STEPS
from bpp.benchmarks.libero.sim import (
    CAMERAS,
    GoalOrder,
    delta_actions,
    initial_states,
    make_env,
    render_now,
    reset_env,
)
from bpp.core.contract import RolloutResult, frames_to_record
from bpp.data.store import EpisodeStore, with_derived
from bpp.errors import UserError

LIFT = 0.05
"""Metres above its settled start that count an object as lifted."""
VIDEO_SIZE = 128
VIDEO_STRIDE = 2
"""Recorded rollouts keep every other control step's frame (and the last): real time in the 10 fps videos, and
half the rendering, which costs about 90 ms a frame on a CPU (as much as the rollout's physics)."""


def observe(env, raw: Mapping, cameras: Sequence[str], size: int) -> dict[str, np.ndarray]:
    """The policy's observation keys (as stored by generation, and the derived ones) from an env's observation
    dictionary."""
    obs = with_derived(
        DERIVED_KEYS,
        {
            "proprio": np.asarray(raw["robot0_proprio-state"], dtype=np.float32),
            "object_state": np.asarray(raw["object-state"], dtype=np.float32),
        },
    )
    for camera in cameras:
        obs[camera] = render_now(env, CAMERAS[camera], size)
    return obs


def goal_terms(problem: str | list) -> list[list]:
    """The terms of the problem's goal (its text, or parsed), in order (a conjunction's parts), e.g.
    ``[["Open", "..."], ["In", ...]]``."""
    goal = section(parse(problem) if isinstance(problem, str) else problem, ":goal")[1:]
    return [t for g in goal for t in (g[1:] if g and g[0] == "And" else [g])]


def goal_objects(problem: str) -> tuple[list[str], list[str]]:
    """(objects the problem's goal puts somewhere, its other movable objects), by name."""
    parsed = parse(problem)
    movable = set(objects(parsed)) - set(objects(parsed, (":fixtures",)))
    terms = goal_terms(parsed)
    moved = [t[1] for t in terms if isinstance(t, list) and len(t) == 3 and t[0] in ("On", "In") and t[1] in movable]
    return moved, sorted(movable - set(moved))


def task_problem(store: EpisodeStore, episode: int) -> str:
    """The BDDL problem of an episode's task, as generation stored it."""
    task = store.tasks[int(store.column("task_index")[episode])]
    problem = task.get("info", {}).get("problem")
    if not problem:
        raise UserError(f"{store.path}: task {task['id']!r} has no BDDL problem; generate the store again")
    return problem


def run_rollouts(
    agent,
    store: EpisodeStore,
    rollouts: Sequence[Mapping],
    max_steps: int = 550,
    record_frames: Sequence[bool | str] | None = None,
    video_size: int = VIDEO_SIZE,
) -> list[RolloutResult]:
    """Rollout i starts from the initial state LIBERO samples with ``rollouts[i]["init_seed"]`` in the problem of
    ``rollouts[i]["target_episode"]``'s task (for LIBERO's own tasks: its initial state number init_seed modulo
    their count, as LIBERO's evaluation uses them) and succeeds when that task's goal holds. `agent` must already
    be reset with the rollouts' contexts. Recorded frames are `video_size` pixels square."""
    spec = agent.data_spec
    cameras = tuple(spec.image_keys)
    unknown = sorted(set(cameras) - set(CAMERAS))
    if unknown:
        raise UserError(f"LIBERO-Gen has no camera {unknown}; its cameras: {', '.join(CAMERAS)}")
    if spec.action_key not in ("action", ABSOLUTE_KEY):
        raise UserError(f"LIBERO-Gen executes actions of key action or {ABSOLUTE_KEY}, not {spec.action_key!r}")
    n = len(rollouts)
    record = [frames_to_record(r) for r in (record_frames if record_frames is not None else [False] * n)]
    envs, obs, eef, heights, orders, ordered = [], [], [], [], [], []
    with tempfile.TemporaryDirectory(prefix="libero-eval-") as folder:
        problems: dict[int, Path] = {}
        starts: dict[int, object] = {}  # LIBERO's own initial states of a task (None for generated tasks)
        lifts: dict[int, tuple[list[str], list[str]]] = {}  # a task's goal objects and other objects
        in_order: dict[int, bool] = {}  # whether a task's several goal terms must be reached in order (Chain)
        try:
            for row, rec in zip(rollouts, record, strict=True):
                episode = int(row["target_episode"])
                task = int(store.column("task_index")[episode])
                if task not in problems:
                    text = task_problem(store, episode)
                    problems[task] = Path(folder) / f"task-{task}.bddl"
                    problems[task].write_text(text)
                    lifts[task] = goal_objects(text)
                    named = store.tasks[task]["info"].get("initial_states")
                    starts[task] = initial_states(named) if named else None
                    in_order[task] = len(store.tasks[task]["info"].get("steps", ())) > 1 and not named
                env = make_env(problems[task], render=bool(cameras) or rec)
                envs.append(env)
                raw = reset_env(env, int(row["init_seed"]))
                states = starts[task]
                if states is not None:
                    raw = env.set_init_state(states[int(row["init_seed"]) % len(states)])
                for _ in range(SETTLE_STEPS):  # as the demonstrations start: objects settled
                    raw, *_ = env.step(np.zeros(7))
                obs.append(observe(env, raw, cameras, spec.image_size))
                eef.append(raw["robot0_eef_pos"])
                heights.append(_Heights(raw, *lifts[task]))
                orders.append(GoalOrder.of(env))
                ordered.append(in_order[task])
            frames = [
                [render_now(env, "agentview", video_size)] if rec == "all" else []
                for env, rec in zip(envs, record, strict=True)
            ]
            done = np.zeros(n, dtype=bool)
            success = np.zeros(n, dtype=bool)
            steps = np.zeros(n, dtype=int)
            final = np.zeros(n, dtype=bool)
            while not done.all():
                actions = agent.act_batch({k: np.stack([o[k] for o in obs]) for k in agent.obs_keys})
                for i in np.flatnonzero(~done):
                    action = np.asarray(actions[i], dtype=np.float64)
                    if spec.action_key == ABSOLUTE_KEY:
                        action = delta_actions(action, eef[i])
                    raw, _, goal, _ = envs[i].step(np.clip(action, -1.0, 1.0))
                    eef[i] = raw["robot0_eef_pos"]
                    steps[i] += 1
                    heights[i].update(raw)
                    obs[i] = observe(envs[i], raw, cameras, spec.image_size)
                    if orders[i] is None:
                        final[i] = bool(goal)  # LIBERO's step returns whether its goal holds after it as `done`
                    else:  # it evaluates the goal's terms once for both
                        orders[i].update()
                        final[i] = orders[i].final
                    success[i] = orders[i].done if ordered[i] else final[i]
                    done[i] = final[i] or steps[i] >= max_steps
                    if (record[i] == "all" and steps[i] % VIDEO_STRIDE == 0) or (record[i] and done[i]):
                        frames[i].append(render_now(envs[i], "agentview", video_size))
        finally:
            for env in envs:
                env.close()
    extras = [heights[i].extra() for i in range(n)]
    for i, order in enumerate(orders):
        if order is not None:
            extras[i]["first_step"] = float(order.first_reached or final[i])
            if ordered[i]:
                extras[i]["final_goal"] = float(final[i])
    return [RolloutResult(float(success[i]), int(steps[i]), extras[i], frames[i]) for i in range(n)]


class _Heights:
    """The highest each object got above its start in one rollout."""

    def __init__(self, raw: Mapping, moved: list[str], others: list[str]):
        self.moved, self.others = moved, others
        self.start = {name: float(raw[f"{name}_pos"][2]) for name in (*moved, *others)}
        self.top = dict(self.start)

    def update(self, raw: Mapping) -> None:
        for name, top in self.top.items():
            self.top[name] = max(top, float(raw[f"{name}_pos"][2]))

    def extra(self) -> dict:
        lifted = [name for name in self.top if self.top[name] - self.start[name] >= LIFT]
        return {
            "lifted": float(any(name in lifted for name in self.moved)),
            "lifted_other": float(any(name in lifted for name in self.others)),
        }
