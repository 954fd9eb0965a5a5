"""A scripted demonstrator that draws any :class:`Drawing` like a person with a mouse, at 10 Hz.

It is closed-loop on the cursor, like a person watching the screen: it travels pen-up to each stroke's start
along a gently bent path, waits for the cursor to arrive, lowers the pen, traces the stroke at its own speed
(a per-demonstration base speed with slow variation), slows down at sharp corners, waits at the stroke's end
for the cursor to catch up, and lifts the pen. After the last stroke it lifts the pen and rests. Small
Gaussian noise on the commanded targets imitates an unsteady hand (never on stroke ends and corners).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bpp.benchmarks.draw import physics
from bpp.drawing.drawing import Drawing, DrawingError
from bpp.drawing.geometry import unit_to_canvas
from bpp.utils import check_fields


@dataclass(frozen=True)
class DemoConfig:
    """Demonstrator parameters, in canvas px and control steps."""

    speed_range: tuple[float, float] = (10.0, 30.0)
    """Base drawing speed, px per control step (100-300 px/s), drawn once per demonstration."""
    speed_wobble: float = 0.2
    """Relative amplitude of the slow speed variation along the drawing."""
    noise_std: float = 2.0
    """Std of the Gaussian noise on commanded targets, px (clipped at 3 std)."""
    corner_angle_deg: float = 50.0
    """Turns sharper than this count as corners, where the hand pauses until the cursor has nearly arrived."""
    corner_tol: float = 0.25
    """At a corner the hand waits until the cursor is within this fraction of a step's travel."""
    corner_max_steps: int = 4
    curve_tol_range: tuple[float, float] = (1.0, 4.0)
    """On curves the hand slows so the cursor's lag cuts a curve by at most about this many px; a slow hand is
    careful (low end), a fast one sloppy (high end), linearly in the demonstration's base speed."""
    arrive_tol: float = 4.0
    """The hand waits until the cursor is this close (px) to a stroke's start or end."""
    max_wait_steps: int = 12
    end_rest_steps: int = 5
    """Pen-up rest after the last stroke."""
    max_steps: int = 400
    """The hand draws faster if needed so a demonstration fits this many steps (the episode limit)."""

    def __post_init__(self):
        lo, hi = self.speed_range
        lo_tol, hi_tol = self.curve_tol_range
        check_fields(
            self,
            ("speed_range", 0 < lo <= hi <= 200, "lo, hi with 0 < lo <= hi <= 200 (px per step)"),
            ("speed_wobble", 0 <= self.speed_wobble < 1, "in [0, 1)"),
            ("noise_std", 0 <= self.noise_std <= 50, "in [0, 50] px"),
            ("corner_angle_deg", 0 <= self.corner_angle_deg <= 180, "in [0, 180]"),
            ("corner_tol", self.corner_tol > 0, "> 0"),
            ("corner_max_steps", self.corner_max_steps >= 0, ">= 0"),
            ("curve_tol_range", 0 < lo_tol <= hi_tol, "lo, hi with 0 < lo <= hi"),
            ("arrive_tol", self.arrive_tol > 0, "> 0 px"),
            ("max_wait_steps", 0 <= self.max_wait_steps <= 1000, "in [0, 1000]"),
            ("end_rest_steps", 0 <= self.end_rest_steps <= 1000, "in [0, 1000]"),
            ("max_steps", 1 <= self.max_steps <= 100_000, "in [1, 100000]"),
        )


@dataclass
class Demonstration:
    """One recorded demonstration: T steps of (state before the step, action)."""

    states: np.ndarray  # (T, 5) float64 [x, y, vx, vy, pen]
    actions: np.ndarray  # (T, 3) float64 [target_x, target_y, pen]
    board_angle: float
    speed: float  # base speed used, px per step

    def __len__(self) -> int:
        return len(self.actions)


def _corner_arclengths(points: np.ndarray, angle_deg: float, scale: float) -> np.ndarray:
    """Arc lengths of sharp turns, measuring direction over `scale` px so dense curves are not corners.

    A vertex turns sharply if the direction from `scale` px behind it to it and from it to `scale` px ahead differ
    by more than `angle_deg`; of sharp vertices closer than `scale` along the stroke only the first counts.
    O(N log N) in the number of vertices.
    """
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    points = points[keep]
    if len(points) < 3:
        return np.zeros(0)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    inner = points[1:-1]
    back = inner - np.stack([np.interp(s[1:-1] - scale, s, points[:, k]) for k in range(2)], axis=1)
    ahead = np.stack([np.interp(s[1:-1] + scale, s, points[:, k]) for k in range(2)], axis=1) - inner
    nb, na = np.linalg.norm(back, axis=1), np.linalg.norm(ahead, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cos = np.clip(np.einsum("ij,ij->i", back, ahead) / (nb * na), -1.0, 1.0)
        sharp = (nb >= 1e-9) & (na >= 1e-9) & (np.degrees(np.arccos(cos)) > angle_deg)
    corners: list[float] = []
    for arclength in s[1:-1][sharp]:
        if not corners or arclength - corners[-1] > scale:
            corners.append(float(arclength))
    return np.asarray(corners)


class _Recorder:
    def __init__(self, state: np.ndarray, noise: float, rng: np.random.Generator, limit: int | None = None):
        self.state = state
        self.limit = limit
        self.states: list[np.ndarray] = []
        self.actions: list[np.ndarray] = []
        self.noise = noise
        self.rng = rng

    def command(self, target: np.ndarray, pen: float, noisy: bool = False) -> None:
        target = np.asarray(target, dtype=np.float64)
        if noisy and self.noise > 0:
            target = target + np.clip(self.rng.normal(0.0, self.noise, 2), -3 * self.noise, 3 * self.noise)
        # Commands are float32-representable so a store holding float32 actions replays them exactly.
        action = np.array([target[0], target[1], pen], dtype=np.float32).astype(np.float64)
        if self.limit is not None and len(self.actions) >= self.limit:
            raise _TooLong
        self.states.append(self.state)
        self.actions.append(action)
        self.state, _ = physics.control_step(self.state, action)

    def wait_until_near(self, target: np.ndarray, pen: float, tol: float, max_steps: int) -> None:
        for _ in range(max_steps):
            if np.linalg.norm(self.state[:2] - target) <= tol and np.linalg.norm(self.state[2:4]) < 10 * tol:
                return
            self.command(target, pen)


def _radius_of_curvature(points: np.ndarray, cum: np.ndarray, window: float) -> np.ndarray:
    """Radius of curvature (px) at each polyline vertex: arc length over turning, measured across `window` px."""
    seg = np.diff(points, axis=0)
    heading = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0])) if len(seg) else np.zeros(0)
    mids = (cum[:-1] + cum[1:]) / 2
    if len(seg) < 2:
        return np.full(len(points), np.inf)
    turn = np.abs(np.interp(cum + window / 2, mids, heading) - np.interp(cum - window / 2, mids, heading))
    return window / np.maximum(turn, 1e-9)


def _plan(
    points: np.ndarray,
    stops: list[float],
    step_len,
    ramp: float,
    curve_tol: float = np.inf,
    min_factor: float = 0.25,
):
    """Targets along a polyline, one per control step, slowing into each stop (an arc length) and landing on it.

    `step_len(k)` is the unhurried travel of step k in px; within `ramp` px of a stop (ahead or behind) the
    travel shrinks like sqrt(distance), as a hand decelerates into a corner and accelerates out of it. On
    curves the travel is also held below sqrt(curve_tol * radius): the cursor's lag cuts a curve of radius R
    by about travel^2 / R px, so this keeps the drawn curve within ~curve_tol px of the intended one.
    Returns (targets (K, 2), is_stop (K,) bool).
    """
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    total = cum[-1]
    radius = _radius_of_curvature(points, cum, window=30.0)

    def at(s: float) -> np.ndarray:
        return np.array([np.interp(s, cum, points[:, 0]), np.interp(s, cum, points[:, 1])])

    targets, is_stop = [], []
    s, behind, k = 0.0, 0.0, 0
    for stop in sorted({*(float(x) for x in stops if 0.0 < x < total), total}):
        while True:
            near = max(min(stop - s, s - behind), 0.0)
            travel = step_len(k) * float(np.clip(np.sqrt(near / ramp), min_factor, 1.0))
            travel = max(min(travel, float(np.sqrt(curve_tol * np.interp(s, cum, radius)))), 0.5)
            k += 1
            if s + travel >= stop:
                s = stop
                targets.append(at(stop))
                is_stop.append(True)
                break
            s += travel
            targets.append(at(s))
            is_stop.append(False)
        behind = stop
    return np.array(targets).reshape(-1, 2), np.array(is_stop, dtype=bool)


def demonstrate(
    drawing: Drawing,
    board_angle: float,
    cursor_start: np.ndarray,
    rng: np.random.Generator,
    cfg: DemoConfig = DemoConfig(),
) -> Demonstration:
    """Draw `drawing` on a board at `board_angle` starting from a resting cursor at `cursor_start`.

    If the demonstration would exceed ``cfg.max_steps`` the hand draws faster (up to 8 tries, x1.3 each). A try is
    abandoned as soon as it runs over; the last is kept up to ``LAST_TRY_FACTOR * cfg.max_steps`` steps, and a
    drawing that needs more raises :class:`DrawingError` (so any drawing costs bounded work).
    """
    speed = float(rng.uniform(*cfg.speed_range))
    seed = int(rng.integers(2**63))
    lo, hi = cfg.speed_range
    care = 0.0 if hi == lo else (speed - lo) / (hi - lo)
    curve_tol = cfg.curve_tol_range[0] + care * (cfg.curve_tol_range[1] - cfg.curve_tol_range[0])
    tries = 8
    for attempt in range(tries):
        limit = cfg.max_steps if attempt < tries - 1 else LAST_TRY_FACTOR * cfg.max_steps
        try:
            return _demonstrate_at(
                drawing, board_angle, cursor_start, np.random.default_rng(seed), cfg, speed, curve_tol, limit
            )
        except _TooLong:
            speed *= 1.3
            curve_tol *= 1.3**2
    raise DrawingError(
        f"{drawing.name}: drawing it takes more than {LAST_TRY_FACTOR * cfg.max_steps} steps even at the "
        f"demonstrator's fastest ({cfg.max_steps} fit an episode); use fewer or shorter strokes"
    )


LAST_TRY_FACTOR = 3
"""The fastest try of a demonstration may take up to this many times ``DemoConfig.max_steps``."""


class _TooLong(Exception):
    """A demonstration try ran over its step limit."""


def _demonstrate_at(
    drawing, board_angle, cursor_start, rng, cfg: DemoConfig, speed: float, curve_tol: float, limit: int | None
):
    strokes = [unit_to_canvas(s, board_angle) for s in drawing.strokes]
    phase = rng.uniform(0, 2 * np.pi)
    wobble_period = rng.uniform(15.0, 40.0)

    def step_len(k: int) -> float:
        return speed * (1.0 + cfg.speed_wobble * np.sin(phase + 2 * np.pi * k / wobble_period))

    ramp = 2.0 * speed
    rec = _Recorder(physics.initial_state(np.asarray(cursor_start, dtype=np.float64)), cfg.noise_std, rng, limit)
    for stroke in strokes:
        start = stroke[0]
        # Pen-up travel along a quadratic Bézier bent sideways by up to 30% of the distance (at most 100 px).
        here = rec.state[:2].copy()
        dist = float(np.linalg.norm(start - here))
        if dist > cfg.arrive_tol:
            normal = np.array([-(start - here)[1], (start - here)[0]]) / dist
            ctrl = (here + start) / 2 + rng.uniform(-1.0, 1.0) * min(0.3 * dist, 100.0) * normal
            t = np.linspace(0.0, 1.0, 64)[:, None]
            travel_path = (1 - t) ** 2 * here + 2 * (1 - t) * t * ctrl + t**2 * start
            targets, _ = _plan(travel_path, [], step_len, ramp)
            for target in targets[:-1]:
                rec.command(target, 0.0, noisy=True)
        rec.command(start, 0.0)  # always at least one pen-up step, so consecutive strokes stay separate
        rec.wait_until_near(start, 0.0, cfg.arrive_tol, cfg.max_wait_steps)
        # Trace the stroke, decelerating into corners and waiting there for the cursor.
        corners = list(_corner_arclengths(stroke, cfg.corner_angle_deg, scale=max(speed, 8.0)))
        targets, is_stop = _plan(stroke, corners, step_len, ramp, curve_tol)
        for target, stop in zip(targets[:-1], is_stop[:-1], strict=True):
            if stop:
                rec.command(target, 1.0)
                rec.wait_until_near(target, 1.0, max(cfg.arrive_tol, cfg.corner_tol * speed), cfg.corner_max_steps)
            else:
                rec.command(target, 1.0, noisy=True)
        rec.command(stroke[-1], 1.0)
        rec.wait_until_near(stroke[-1], 1.0, cfg.arrive_tol, cfg.max_wait_steps)
    for _ in range(cfg.end_rest_steps):
        rec.command(rec.actions[-1][:2], 0.0)
    return Demonstration(np.array(rec.states), np.array(rec.actions), float(board_angle), speed)


def replay_paths(states: np.ndarray, actions: np.ndarray) -> list[np.ndarray]:
    """The canvas polylines inked by each pen-down step of a recorded episode (exact replay of the physics)."""
    paths = []
    for state, action in zip(states, actions, strict=True):
        _, path = physics.control_step(state, action)
        if action[2] > physics.PEN_THRESHOLD:
            paths.append(path)
    return paths
