"""The studio's core, without HTTP: sessions, prompts, checkpoints and live rollouts.

A *session* is one client (a browser tab, a phone, a script); it sees only its own prompts and rollouts, and ids
are random, so one session cannot guess another's. A *prompt* is one demonstration, kept as a one-episode store
in the studio's private working folder (so that training's context builder and evaluation's target are used as
they are): drawn by a person (commanded cursor targets and pen at the env's 10 Hz), a stored demonstration of
the unseen drawings, or a drawing (strokes or a JSON/SVG file's content) demonstrated by the built-in
demonstrator. A *rollout* is a policy drawing that prompt on a board at a new angle, in a thread of its own; its
steps are kept as events that clients read as they come. A rollout nobody reads for ``Limits.abandon_s`` seconds
is stopped.

Nothing a client sends is used as a file path: prompts and uploads are written under server-chosen names.
"""

from __future__ import annotations

import hashlib
import secrets
import shutil
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from bpp.benchmarks.draw import physics
from bpp.benchmarks.draw.demonstrator import DemoConfig, Demonstration, demonstrate
from bpp.benchmarks.draw.drawing import Drawing, DrawingError
from bpp.benchmarks.draw.geometry import CANVAS_SIZE, MAX_BOARD_ANGLE, canvas_to_unit
from bpp.data.store import EpisodeStore, EpisodeWriter

BENCHMARK = "drawanything"
END_REST_STEPS = DemoConfig().end_rest_steps
"""Pen-up steps appended to a drawn prompt, as the demonstrator rests after its last stroke."""


KEEP_FINISHED_ROLLOUTS = 32
"""Finished rollouts a session keeps (for their results and downloads); older ones are forgotten."""


class StudioError(ValueError):
    """A request the studio refuses; ``field`` names the offending input, ``status`` is the HTTP status to give."""

    def __init__(self, message: str, field: str = "", status: int = 400):
        super().__init__(message)
        self.field, self.status = field, status


@dataclass(frozen=True)
class Limits:
    """What one studio accepts (every limit is checked before work starts)."""

    max_body_bytes: int = 2 << 20
    """Largest request body."""
    max_prompt_steps: int = 800
    """Longest prompt (BPP's learned prompt positions cover 800 steps)."""
    max_rollout_steps: int = 1000
    max_prompts_per_session: int = 32
    max_rollouts_per_session: int = 2
    """Rollouts of one session running at once."""
    max_rollouts: int = 8
    """Rollouts running at once in the whole studio (they share the CPU)."""
    max_sessions: int = 64
    abandon_s: float = 30.0
    """A running rollout whose events no client has read for this long is stopped."""
    session_idle_s: float = 3600.0
    """A session unused for this long is forgotten (its prompts deleted)."""


@dataclass
class CheckpointInfo:
    id: str
    label: str
    method: str
    step: int
    path: Path = field(repr=False)

    def public(self) -> dict:
        return {"id": self.id, "label": self.label, "method": self.method, "step": self.step}


@dataclass
class Prompt:
    id: str
    source: str
    board_angle: float
    steps: int
    store: EpisodeStore = field(repr=False)
    label: str = ""

    def public(self) -> dict:
        return {
            "id": self.id,
            "source": self.source,
            "label": self.label,
            "board_angle": self.board_angle,
            "steps": self.steps,
        }


@dataclass
class Rollout:
    id: str
    prompt: Prompt
    checkpoint: CheckpointInfo
    board_angle: float
    seed: int
    max_steps: int
    frames: int = 0
    """Side of the rendered frame sent with every step event as a base64 PNG (0: none)."""
    events: list = field(default_factory=list)
    status: str = "starting"
    """starting, running, done, stopped (asked to), abandoned (nobody read it), error."""
    error: str = ""
    actions: list = field(default_factory=list)
    best: float = float("inf")
    last_read: float = field(default_factory=time.monotonic)
    stop: threading.Event = field(default_factory=threading.Event)

    @property
    def running(self) -> bool:
        return self.status in ("starting", "running")

    @property
    def counted(self) -> bool:
        """Whether it counts against the rollout limits: running and not asked to stop (it stops at its next step;
        the thread pool bounds the CPU meanwhile), so that pressing Run again is not refused."""
        return self.running and not self.stop.is_set()

    def drop_frames(self) -> None:
        """Forget the frames of sent events (they are only for the live stream; a finished rollout keeps the rest)."""
        for event in self.events:
            event.pop("frame", None)

    def public(self) -> dict:
        return {
            "id": self.id,
            "status": self.status,
            "error": self.error,
            "prompt": self.prompt.id,
            "checkpoint": self.checkpoint.id,
            "method": self.checkpoint.method,
            "board_angle": self.board_angle,
            "seed": self.seed,
            "steps": len(self.actions),
            "best_chamfer": None if not np.isfinite(self.best) else round(self.best, 3),
        }


@dataclass
class Session:
    id: str
    folder: Path
    prompts: dict[str, Prompt | None] = field(default_factory=dict)
    rollouts: dict[str, Rollout] = field(default_factory=dict)
    last_used: float = field(default_factory=time.monotonic)


def find_checkpoints(roots) -> list[CheckpointInfo]:
    """DrawAnything runs (folders with ``checkpoints/last``, or checkpoint folders) under `roots`, newest first."""
    from bpp.checkpoint import read_state, resolve_checkpoint

    found: dict[Path, CheckpointInfo] = {}
    for root in map(Path, roots):
        if not root.exists():
            continue
        candidates = [root] if (root / "checkpoints" / "last").is_file() else []
        candidates += [p.parent.parent for p in sorted(root.glob("*/checkpoints/last"))]
        candidates += [p.parent.parent for p in sorted(root.glob("*/*/checkpoints/last"))]
        for run in candidates:
            try:
                ckpt = resolve_checkpoint(run)
                state = read_state(ckpt)
            except (OSError, ValueError):
                continue
            if state.get("dataset", {}).get("benchmark") != BENCHMARK or ckpt.resolve() in found:
                continue
            ident = hashlib.sha256(str(ckpt.resolve()).encode()).hexdigest()[:12]
            label = f"{state['method']} · {run.name} · step {state['step']}"
            found[ckpt.resolve()] = CheckpointInfo(ident, label, state["method"], int(state["step"]), ckpt)
    return sorted(found.values(), key=lambda c: c.path.stat().st_mtime, reverse=True)


class Studio:
    """Sessions, prompts and rollouts of one studio server. Thread-safe."""

    def __init__(
        self, checkpoints: list[CheckpointInfo], workdir: Path, limits: Limits = Limits(), data_dir: Path | None = None
    ):
        self.checkpoints = {c.id: c for c in checkpoints}
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.limits = limits
        self.data_dir = data_dir
        self.sessions: dict[str, Session] = {}
        self.lock = threading.RLock()
        self.models: dict[str, object] = {}
        self._model_locks: dict[str, threading.Lock] = {}
        self._human_lock = threading.Lock()
        self.pool = ThreadPoolExecutor(max_workers=limits.max_rollouts, thread_name_prefix="rollout")
        self._human: EpisodeStore | None = None

    # ------------------------------------------------------------------------------------------ sessions
    def new_session(self) -> str:
        """A new session; when the studio is full, the least recently used idle session (none of its rollouts
        running) is forgotten to make room."""
        with self.lock:
            forgotten = self._forget_idle()
            if len(self.sessions) >= self.limits.max_sessions:
                idle = [s for s in self.sessions.values() if not any(r.running for r in s.rollouts.values())]
                if not idle:
                    raise StudioError(
                        f"the studio has {len(self.sessions)} busy sessions, its limit; try again later", "session", 429
                    )
                oldest = min(idle, key=lambda s: s.last_used)
                forgotten.append(self.sessions.pop(oldest.id))
            sid = secrets.token_hex(16)
            self.sessions[sid] = Session(sid, self.workdir / sid)
        for session in forgotten:  # outside the lock: deleting files must not hold up requests
            shutil.rmtree(session.folder, ignore_errors=True)
        return sid

    def end_session(self, sid: str) -> None:
        """Stop the session's rollouts and forget it (its prompts are deleted)."""
        session = self.session(sid)
        with self.lock:
            self.sessions.pop(sid, None)
        for rollout in session.rollouts.values():
            rollout.stop.set()
        shutil.rmtree(session.folder, ignore_errors=True)

    def session(self, sid: str) -> Session:
        with self.lock:
            session = self.sessions.get(sid)
            if session is None:
                raise StudioError("unknown or expired session; start a new one", "session", 404)
            session.last_used = time.monotonic()
            return session

    def _forget_idle(self) -> list[Session]:
        """Drop sessions unused for ``session_idle_s`` (none of their rollouts running); returns them, so that
        their folders are deleted outside the lock."""
        now = time.monotonic()
        forgotten = []
        for sid, session in list(self.sessions.items()):
            idle = now - session.last_used > self.limits.session_idle_s
            if idle and not any(r.running for r in session.rollouts.values()):
                forgotten.append(self.sessions.pop(sid))
        return forgotten

    def close(self) -> None:
        for session in list(self.sessions.values()):
            for rollout in session.rollouts.values():
                rollout.stop.set()
        self.pool.shutdown(wait=True, cancel_futures=True)

    # ------------------------------------------------------------------------------------------- prompts
    def human_store(self) -> EpisodeStore:
        """The 50 unseen human-made drawings (generated on first use)."""
        with self._human_lock:  # two first calls must not generate it twice into one folder
            if self._human is None:
                from bpp.benchmarks.registry import get_benchmark

                benchmark = get_benchmark(BENCHMARK)
                self._human = benchmark.task_set("human", self.data_dir or benchmark.default_data_dir).store
        return self._human

    def stored_prompts(self) -> list[dict]:
        store = self.human_store()
        episodes = store.task_episodes()
        return [{"task": t, "id": task["id"], "episodes": len(episodes[t])} for t, task in enumerate(store.tasks)]

    def _new_prompt(
        self, sid: str, source: str, label: str, drawing: Drawing, demo: Demonstration, field: str
    ) -> Prompt:
        """Store `demo` as a prompt of session `sid`; `field` names the input it came from (for errors)."""
        from bpp.benchmarks.draw.dataset import episode_steps, strokes_array

        session = self.session(sid)
        if len(demo) > self.limits.max_prompt_steps:
            raise StudioError(
                f"demonstrating it takes {len(demo)} steps; a prompt has at most {self.limits.max_prompt_steps}",
                field,
                422,
            )
        with self.lock:  # the slot is reserved now, so concurrent uploads cannot pass the limit
            if len(session.prompts) >= self.limits.max_prompts_per_session:
                raise StudioError(f"this session has {len(session.prompts)} prompts, its limit", "prompt", 429)
            pid = secrets.token_hex(8)
            session.prompts[pid] = None
        try:
            path = session.folder / f"prompt-{pid}.zarr"
            with EpisodeWriter(path, benchmark=BENCHMARK, config={"studio": source}) as writer:
                task = writer.add_task(drawing.id, {"source": source}, strokes=strokes_array(drawing))
                writer.add_episode(episode_steps(demo), task, board_angle=demo.board_angle, speed=demo.speed)
            prompt = Prompt(pid, source, float(demo.board_angle), len(demo), EpisodeStore(path), label)
        except BaseException:
            session.prompts.pop(pid, None)
            raise
        session.prompts[pid] = prompt
        return prompt

    def add_drawn_prompt(self, sid: str, samples, board_angle: float) -> Prompt:
        """A person's demonstration: (N, 3) samples [x, y, pen] in canvas px at 10 Hz, the cursor targets they
        commanded (the env's action), replayed through the env's physics from the first sample."""
        samples = np.asarray(samples, dtype=np.float64)
        if samples.ndim != 2 or samples.shape[1] != 3 or len(samples) < 2:
            raise StudioError("samples must be a list of at least 2 [x, y, pen] triples", "samples", 422)
        if not np.all(np.isfinite(samples)) or samples[:, :2].min() < 0 or samples[:, :2].max() > CANVAS_SIZE:
            raise StudioError(f"sample positions must be finite canvas pixels in [0, {CANVAS_SIZE}]", "samples", 422)
        if not np.all(np.isin(samples[:, 2], (0.0, 1.0))):
            raise StudioError("each sample's pen must be 0 (up) or 1 (down)", "samples", 422)
        if not samples[:, 2].any():
            raise StudioError("the drawing has no pen-down sample: draw at least one stroke", "samples", 422)
        if len(samples) + END_REST_STEPS > self.limits.max_prompt_steps:
            raise StudioError(
                f"{len(samples)} samples; a prompt has at most {self.limits.max_prompt_steps - END_REST_STEPS}",
                "samples",
                413,
            )
        actions = (
            np.concatenate([samples, np.c_[np.repeat(samples[-1:, :2], END_REST_STEPS, 0), np.zeros(END_REST_STEPS)]])
            .astype(np.float32)
            .astype(np.float64)
        )
        state = physics.initial_state(actions[0, :2])
        states = []
        for action in actions:
            states.append(state)
            state, _ = physics.control_step(state, action)
        states = np.array(states)
        demo = Demonstration(states, actions, float(board_angle), speed=0.0)
        return self._new_prompt(
            sid, "drawn", "your drawing", _drawing_of(states, actions, board_angle), demo, "samples"
        )

    def add_strokes_prompt(self, sid: str, strokes, board_angle: float, seed: int = 0) -> Prompt:
        """A drawing (unit-square strokes, y up) demonstrated by the built-in demonstrator at `board_angle`."""
        from bpp.benchmarks.draw.files import bounded

        try:
            drawing = bounded(Drawing.from_strokes("drawing", strokes, source="strokes"), "strokes")
        except DrawingError as err:
            raise StudioError(str(err), "strokes", 422) from None
        return self._demonstrated(sid, drawing, board_angle, seed, "strokes", "strokes")

    def add_file_prompt(self, sid: str, name: str, text: str, board_angle: float, seed: int = 0) -> Prompt:
        """The first drawing of an uploaded JSON stroke or SVG file's content (`name` only chooses the format)."""
        from bpp.benchmarks.draw.files import load_drawings

        suffix = Path(name).suffix.lower()
        if suffix not in (".json", ".svg"):
            raise StudioError(f"file name {name!r}: expected a .json or .svg drawing file", "name", 422)
        session = self.session(sid)
        session.folder.mkdir(parents=True, exist_ok=True)
        upload = session.folder / f"upload-{secrets.token_hex(8)}{suffix}"
        upload.write_text(text, encoding="utf-8")
        try:
            drawing = load_drawings([upload])[0]
        except DrawingError as err:
            raise StudioError(str(err).replace(str(upload), name), "text", 422) from None
        finally:
            upload.unlink(missing_ok=True)
        return self._demonstrated(sid, drawing, board_angle, seed, f"file {name}", "text")

    def add_stored_prompt(self, sid: str, task: int, demo: int = 0) -> Prompt:
        """Demonstration `demo` of unseen drawing `task` (as ``bpp eval`` prompts it)."""
        from bpp.benchmarks.draw.dataset import task_drawing

        store = self.human_store()
        if not 0 <= task < store.num_tasks:
            raise StudioError(f"task must be in [0, {store.num_tasks}), got {task}", "task", 422)
        episodes = store.task_episodes()[task]
        if not 0 <= demo < len(episodes):
            raise StudioError(f"demo must be in [0, {len(episodes)}), got {demo}", "demo", 422)
        episode = int(episodes[demo])
        steps = store.episode(episode, ("state", "action"))
        angle = float(store.column("board_angle")[episode])
        demo_obj = Demonstration(steps["state"], steps["action"].astype(np.float64), angle, 0.0)
        drawing = task_drawing(store, task)
        return self._new_prompt(sid, "stored", f"{drawing.id} (demo {demo})", drawing, demo_obj, "task")

    def _demonstrated(
        self, sid: str, drawing: Drawing, board_angle: float, seed: int, source: str, field: str
    ) -> Prompt:
        rng = np.random.default_rng(seed)
        start = rng.uniform(50.0, 450.0, size=2)
        try:
            demo = demonstrate(drawing, float(board_angle), start, rng, DemoConfig())
        except DrawingError as err:
            raise StudioError(str(err), field, 422) from None
        return self._new_prompt(sid, source, drawing.id, drawing, demo, field)

    def prompt(self, sid: str, pid: str) -> Prompt:
        prompt = self.session(sid).prompts.get(pid)  # None while it is still being written
        if prompt is None:
            raise StudioError(f"no prompt {pid!r} in this session", "prompt_id", 404)
        return prompt

    def prompt_task_file(self, sid: str, pid: str) -> dict:
        """The prompt's drawing in the JSON stroke format, for ``bpp eval --files``."""
        from bpp.benchmarks.draw.dataset import task_drawing

        drawing = task_drawing(self.prompt(sid, pid).store, 0)
        return {"drawings": [{**drawing.to_json(), "id": f"studio-{pid}"}]}

    # ------------------------------------------------------------------------------------------ rollouts
    def start_rollout(
        self,
        sid: str,
        pid: str,
        checkpoint_id: str,
        board_angle: float | None,
        seed: int,
        max_steps: int,
        frames: int = 0,
    ) -> Rollout:
        session = self.session(sid)
        prompt = self.prompt(sid, pid)
        checkpoint = self.checkpoints.get(checkpoint_id)
        if checkpoint is None:
            raise StudioError(f"no checkpoint {checkpoint_id!r}; GET /api/checkpoints lists them", "checkpoint_id", 404)
        if not 1 <= max_steps <= self.limits.max_rollout_steps:
            raise StudioError(f"max_steps must be in [1, {self.limits.max_rollout_steps}]", "max_steps", 422)
        if frames not in (0, 64, 128, 256):
            raise StudioError(f"frames must be 0 (none), 64, 128 or 256, got {frames}", "frames", 422)
        if board_angle is None:
            board_angle = float(np.random.default_rng(seed).uniform(-MAX_BOARD_ANGLE, MAX_BOARD_ANGLE))
        with self.lock:
            mine = sum(r.counted for r in session.rollouts.values())
            total = sum(r.counted for s in self.sessions.values() for r in s.rollouts.values())
            if mine >= self.limits.max_rollouts_per_session:
                raise StudioError(f"this session already runs {mine} rollouts, its limit", "rollout", 429)
            if total >= self.limits.max_rollouts:
                raise StudioError(f"the studio runs {total} rollouts, its limit; try again shortly", "rollout", 429)
            rollout = Rollout(
                secrets.token_hex(8), prompt, checkpoint, float(board_angle), int(seed), int(max_steps), int(frames)
            )
            session.rollouts[rollout.id] = rollout
            finished = [rid for rid, r in session.rollouts.items() if not r.running]
            for rid in finished[: max(0, len(finished) - KEEP_FINISHED_ROLLOUTS)]:  # oldest first (dict order)
                del session.rollouts[rid]
        self.pool.submit(self._run, rollout)
        return rollout

    def rollout(self, sid: str, rid: str) -> Rollout:
        rollout = self.session(sid).rollouts.get(rid)
        if rollout is None:
            raise StudioError(f"no rollout {rid!r} in this session", "rollout_id", 404)
        rollout.last_read = time.monotonic()
        return rollout

    def _model(self, checkpoint: CheckpointInfo):
        """The checkpoint's model, loaded once (under a lock of its own: loading must not hold up requests)."""
        with self.lock:
            loading = self._model_locks.setdefault(checkpoint.id, threading.Lock())
        with loading:
            if checkpoint.id not in self.models:
                from bpp.checkpoint import Checkpoint

                self.models[checkpoint.id] = Checkpoint.load(checkpoint.path, use_ema=True).build_model()
            return self.models[checkpoint.id]

    def _run(self, rollout: Rollout) -> None:
        try:
            self._steps(rollout)
        except Exception as err:  # noqa: BLE001 - reported to the client, the studio goes on
            rollout.error = f"{type(err).__name__}: {err}"
            rollout.events.append({"type": "end", "status": "error", "error": rollout.error})
            rollout.status = "error"

    def _steps(self, rollout: Rollout) -> None:
        import torch

        from bpp.benchmarks.draw.env import ACTION_FRAMES, DrawEnv
        from bpp.benchmarks.draw.rollouts import prompt_target
        from bpp.benchmarks.registry import get_benchmark
        from bpp.data.contexts import task_context
        from bpp.policies.agent import PolicyAgent

        agent = PolicyAgent(self._model(rollout.checkpoint), record_attention=True)
        spec = agent.data_spec
        store = rollout.prompt.store
        agent.reset(task_context(store, 0, spec, get_benchmark(BENCHMARK).frames), rollout.seed)
        env = DrawEnv(
            image_size=spec.image_size if spec.image_keys else None,
            max_episode_steps=rollout.max_steps,
            action_frame=ACTION_FRAMES[spec.action_key],
            render_mode="rgb_array" if rollout.frames else None,
            render_size=rollout.frames or CANVAS_SIZE,
        )
        target = prompt_target(store, 0)
        obs, _ = env.reset(seed=rollout.seed, options={"board_angle": rollout.board_angle, "target": target})
        rollout.status = "running"
        rollout.events.append(
            {
                "type": "start",
                "board_angle": rollout.board_angle,
                "cursor": env.state[:2].tolist(),
                "prompt_steps": rollout.prompt.steps,
            }
        )
        calls = 0
        done = False
        status = "done"
        while not done:
            if rollout.stop.is_set():
                status = "stopped"
                break
            if time.monotonic() - rollout.last_read > self.limits.abandon_s:
                status = "abandoned"
                break
            with torch.no_grad():
                action = agent.act(obs)
            before = env.state.copy()
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
            rollout.actions.append(np.asarray(action, dtype=np.float64).tolist())
            rollout.best = float(info["best_chamfer"])
            event = {
                "type": "step",
                "step": env.steps,
                "action": [round(float(a), 4) for a in action],
                "cursor": [round(float(v), 2) for v in env.state[:2]],
                "pen": int(env.state[4] > 0.5),
                "from": [round(float(v), 2) for v in before[:2]],
                "chamfer": round(float(info["chamfer"]), 3),
                "best_chamfer": round(float(info["best_chamfer"]), 3),
            }
            if rollout.frames:
                event["frame"] = _png_base64(env.render())
            if len(agent.attention_log) > calls:
                calls = len(agent.attention_log)
                event["attention"] = [round(float(a), 4) for a in agent.attention_log[-1][0]]
            rollout.events.append(event)
        best = rollout.public()["best_chamfer"]
        rollout.events.append({"type": "end", "status": status, "best_chamfer": best, "steps": len(rollout.actions)})
        rollout.status = status  # after the end event: a stream that sees the rollout finished has it to send
        if status == "abandoned":
            rollout.drop_frames()

    def stop_rollout(self, sid: str, rid: str) -> Rollout:
        rollout = self.rollout(sid, rid)
        rollout.stop.set()
        return rollout

    def episode(self, sid: str, rid: str) -> dict:
        """A finished (or stopped) rollout as JSON: its prompt, board angle, seed, actions and score."""
        rollout = self.rollout(sid, rid)
        return {
            **rollout.public(),
            "prompt": rollout.prompt.public(),
            "actions": rollout.actions,
            "limits": asdict(self.limits),
        }

    def animation(self, sid: str, rid: str, path: Path, size: int = 256) -> Path:
        """Replay a rollout's actions (the physics is deterministic) into a GIF or MP4 at `path` (server-chosen)."""
        from bpp.benchmarks.draw.env import ACTION_FRAMES, DrawEnv
        from bpp.benchmarks.draw.rollouts import prompt_target
        from bpp.media import save_animation

        rollout = self.rollout(sid, rid)
        if rollout.running:
            raise StudioError("the rollout is still running", "rollout_id", 409)
        spec_frame = ACTION_FRAMES[self._model(rollout.checkpoint).data_spec().action_key]
        env = DrawEnv(
            image_size=None,
            max_episode_steps=max(1, len(rollout.actions)),
            render_mode="rgb_array",
            render_size=size,
            action_frame=spec_frame,
            early_stop=False,
        )
        target = prompt_target(rollout.prompt.store, 0)
        env.reset(seed=rollout.seed, options={"board_angle": rollout.board_angle, "target": target})
        frames = [env.render()]
        for action in rollout.actions:
            env.step(np.asarray(action))
            frames.append(env.render())
        return save_animation(frames, path)


def _png_base64(frame: np.ndarray) -> str:
    import base64
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(frame).save(buffer, format="PNG")
    return base64.b64encode(buffer.getvalue()).decode()


def _drawing_of(states: np.ndarray, actions: np.ndarray, board_angle: float) -> Drawing:
    """The strokes a drawn prompt inked (cursor positions while the pen was down), in the board's unit square."""
    pen = states[1:, 4] > 0.5
    cursor = canvas_to_unit(states[1:, :2], board_angle)
    strokes, current = [], []
    for down, point in zip(pen, cursor, strict=True):
        if down:
            current.append(np.clip(point, 0.0, 1.0))
        elif current:
            strokes.append(np.array(current))
            current = []
    if current:
        strokes.append(np.array(current))
    if not strokes:
        raise StudioError("the drawing inked nothing: hold the button down while you move", "samples", 422)
    return Drawing.from_strokes("drawn", strokes, source="studio")
