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

Every token holder may be an abuser, so every kind of work has a bound per session and in total (:class:`Limits`):
prompts are prepared a few at a time and refused by cheap checks before costly ones, a rollout's rendered frames wait
for their reader (a rollout runs ahead of its reader by at most ``Limits.frame_backlog`` frames), events are kept as
compact JSON text, animations are rendered from a bounded number of frames, cached, and stopped when their client
leaves, and places are shared fairly between client addresses (a session whose work is under way is never evicted). What
a burst of work frees goes back to the system within ``RELEASE_EVERY_S`` (:mod:`bpp.benchmarks.draw.studio.memory`).
"""

from __future__ import annotations

import base64
import io
import json
import secrets
import shutil
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

import numpy as np
from PIL import Image

from bpp.benchmarks.draw import physics
from bpp.benchmarks.draw.dataset import episode_steps
from bpp.benchmarks.draw.demonstrator import LAST_TRY_FACTOR, DemoConfig, Demonstration, demonstrate, replay_paths
from bpp.benchmarks.draw.env import ACTION_FRAMES, DrawEnv
from bpp.benchmarks.draw.rollouts import prompt_target
from bpp.benchmarks.draw.studio.animation import Cancelled, render_animation
from bpp.benchmarks.draw.studio.memory import RELEASE_EVERY_S, release_memory
from bpp.benchmarks.draw.studio.state import (
    BENCHMARK,
    CheckpointInfo,
    FairSlots,
    Limits,
    Prompt,
    Rollout,
    Session,
    StudioError,
)
from bpp.core.registry import get_benchmark
from bpp.data.contexts import task_context
from bpp.data.store import EpisodeStore, EpisodeWriter
from bpp.drawing.drawing import Drawing, DrawingError, strokes_array, task_drawing
from bpp.drawing.files import MAX_POINTS, bounded, load_drawings
from bpp.drawing.geometry import BOARD_SIZE, CANVAS_SIZE, MAX_BOARD_ANGLE, canvas_to_unit

END_REST_STEPS = DemoConfig().end_rest_steps
"""Pen-up steps appended to a drawn prompt, as the demonstrator rests after its last stroke."""


KEEP_FINISHED_ROLLOUTS = 8
"""Finished rollouts a session keeps (for their results and downloads); older ones are forgotten."""
FASTEST_DEMO_STEP_PX = DemoConfig().speed_range[1] * (1 + DemoConfig().speed_wobble) * 1.3**7
"""The farthest the demonstrator's hand moves in one step, at its fastest try (it speeds up x1.3 per try)."""


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
        self._prompt_jobs = FairSlots(limits.max_prompt_jobs, limits.max_waiting_prompts)
        self._renders = threading.BoundedSemaphore(limits.max_renders)
        self.streams = 0
        self._closing = threading.Event()
        threading.Thread(target=self._release_memory_regularly, name="studio-memory", daemon=True).start()

    # ------------------------------------------------------------------------------------------ sessions
    def new_session(self, client: str = "") -> str:
        """A new session for the client at address `client`, the places shared fairly between addresses. A client at
        ``max_sessions_per_client`` replaces one of its own sessions; when the studio is full, the new session
        replaces one of the client that holds the most. Either way the one replaced is the least valuable
        (:meth:`Session.worth`: one that holds nothing before one that holds work, then the least recently used),
        and a session whose work is under way (:meth:`Session.busy`) is never replaced: when every candidate is
        busy, the new session is refused (429). So a flood of new sessions from one address replaces only its
        own, and a client with one session keeps it unless every address holds one."""
        with self.lock:
            forgotten = self._forget_idle()
            mine = [s for s in self.sessions.values() if s.client == client]
            if len(mine) >= self.limits.max_sessions_per_client:  # a client makes room only among its own
                forgotten.append(self._evict([mine], f"this client's {len(mine)} sessions"))
            elif len(self.sessions) >= self.limits.max_sessions:
                held = Counter(s.client for s in self.sessions.values())
                by_count: dict[int, list[Session]] = {}  # the sessions of the clients that hold n, by n
                for session in self.sessions.values():
                    by_count.setdefault(held[session.client], []).append(session)
                largest_first = [by_count[n] for n in sorted(by_count, reverse=True)]
                forgotten.append(self._evict(largest_first, f"the studio's {len(self.sessions)} sessions"))
            sid = secrets.token_hex(16)
            self.sessions[sid] = Session(sid, self.workdir / sid, client=client)
        for session in forgotten:  # outside the lock: deleting files must not hold up requests
            self._discard(session)
        return sid

    def _evict(self, groups: list[list[Session]], whose: str) -> Session:
        """Forget the least valuable session that is not busy of the first group that has one, or refuse (429)."""
        for group in groups:
            idle = [s for s in group if not s.busy()]
            if idle:
                return self.sessions.pop(min(idle, key=Session.worth).id)
        raise StudioError(f"{whose} are all busy; end one (DELETE /api/session) or try later", "session", 429)

    def end_session(self, sid: str) -> None:
        """Stop the session's rollouts and forget it (its prompts are deleted)."""
        session = self.session(sid)
        with self.lock:
            self.sessions.pop(sid, None)
        self._discard(session)

    @staticmethod
    def _discard(session: Session) -> None:
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

    def session_info(self, sid: str) -> dict:
        """What the session holds (the page's keep-alive asks for it)."""
        session = self.session(sid)
        prompts = [p.public() for p in list(session.prompts.values()) if p is not None]
        rollouts = [r.public() for r in list(session.rollouts.values())]
        return {"session": sid, "prompts": prompts, "rollouts": rollouts, "limits": asdict(self.limits)}

    def _forget_idle(self) -> list[Session]:
        """Drop sessions unused for ``session_idle_s`` (none of their rollouts running); returns them, so that
        their folders are deleted outside the lock."""
        now = time.monotonic()
        forgotten = []
        for sid, session in list(self.sessions.items()):
            idle = now - session.last_used > self.limits.session_idle_s
            if idle and not session.busy():
                forgotten.append(self.sessions.pop(sid))
        return forgotten

    def _release_memory_regularly(self) -> None:
        """Every ``RELEASE_EVERY_S``, give the memory freed meanwhile back to the system (:func:`release_memory`):
        after a burst of work, within that time the studio's memory is back to what its remaining sessions hold."""
        while not self._closing.wait(RELEASE_EVERY_S):
            release_memory()

    def close(self) -> None:
        self._closing.set()
        for session in list(self.sessions.values()):
            for rollout in session.rollouts.values():
                rollout.stop.set()
        self.pool.shutdown(wait=True, cancel_futures=True)

    def open_stream(self, sid: str, rollout: Rollout) -> None:
        """Count an event stream against the limits (:meth:`close_stream` when it ends)."""
        session = self.session(sid)
        with self.lock:
            if session.streams >= self.limits.max_streams_per_session:
                raise StudioError(f"this session has {session.streams} event streams open, its limit", "stream", 429)
            if self.streams >= self.limits.max_streams:
                raise StudioError(f"the studio has {self.streams} event streams open, its limit", "stream", 429)
            session.streams += 1
            self.streams += 1
            rollout.readers += 1

    def close_stream(self, sid: str, rollout: Rollout) -> None:
        with self.lock:
            session = self.sessions.get(sid)
            if session is not None:
                session.streams -= 1
            self.streams -= 1
            rollout.readers -= 1
            if not rollout.running and not rollout.readers:
                rollout.drop_frames()

    # ------------------------------------------------------------------------------------------- prompts
    def human_store(self) -> EpisodeStore:
        """The 50 unseen human-made drawings (generated on first use)."""
        with self._human_lock:  # two first calls must not generate it twice into one folder
            if self._human is None:
                benchmark = get_benchmark(BENCHMARK)
                self._human = benchmark.task_set("human", self.data_dir or benchmark.default_data_dir).store
        return self._human

    def stored_prompts(self) -> list[dict]:
        store = self.human_store()
        episodes = store.task_episodes()
        return [{"task": t, "id": task["id"], "episodes": len(episodes[t])} for t, task in enumerate(store.tasks)]

    def _preparing(self, sid: str):
        """A context in which session `sid` prepares one prompt: one per session, ``max_prompt_jobs`` in all, shared
        fairly between client addresses (:class:`FairSlots`: a prompt waits up to ``Limits.prompt_wait_s`` for a
        place, then 429; one waits per address, ``Limits.max_waiting_prompts`` in all)."""
        studio = self

        class _Job:
            def __enter__(self):
                session = studio.session(sid)
                with studio.lock:
                    if session.preparing:
                        raise StudioError("this session is already preparing a prompt; wait for it", "prompt", 429)
                    if len(session.prompts) >= studio.limits.max_prompts_per_session:
                        raise StudioError(
                            f"this session has {len(session.prompts)} prompts, its limit; delete one "
                            "(DELETE /api/prompts/{id})",
                            "prompt",
                            429,
                        )
                    session.preparing = True  # before waiting: the session's next prompt is refused meanwhile
                if not studio._prompt_jobs.acquire(session.client, studio.limits.prompt_wait_s):
                    session.preparing = False
                    raise StudioError("the studio is busy preparing other prompts; try again shortly", "prompt", 429)
                self.session = session
                return session

            def __exit__(self, *_):
                self.session.preparing = False
                studio._prompt_jobs.release()

        return _Job()

    def _new_prompt(
        self, sid: str, source: str, label: str, drawing: Drawing, demo: Demonstration, field: str
    ) -> Prompt:
        """Store `demo` as a prompt of session `sid`; `field` names the input it came from (for errors)."""
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
            store = EpisodeStore(path)
            ink = _polylines(replay_paths(demo.states, demo.actions))
            prompt = Prompt(pid, source, float(demo.board_angle), len(demo), store, label, ink, prompt_target(store, 0))
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
        if len(samples) + END_REST_STEPS > self.limits.max_prompt_steps:
            raise StudioError(
                f"{len(samples)} samples; a prompt has at most {self.limits.max_prompt_steps - END_REST_STEPS}",
                "samples",
                413,
            )
        if not np.all(np.isfinite(samples)) or samples[:, :2].min() < 0 or samples[:, :2].max() > CANVAS_SIZE:
            raise StudioError(f"sample positions must be finite canvas pixels in [0, {CANVAS_SIZE}]", "samples", 422)
        if not np.all(np.isin(samples[:, 2], (0.0, 1.0))):
            raise StudioError("each sample's pen must be 0 (up) or 1 (down)", "samples", 422)
        if not samples[:, 2].any():
            raise StudioError("the drawing has no pen-down sample: draw at least one stroke", "samples", 422)
        with self._preparing(sid):
            actions = (
                np.concatenate(
                    [samples, np.c_[np.repeat(samples[-1:, :2], END_REST_STEPS, 0), np.zeros(END_REST_STEPS)]]
                )
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
            drawing = _drawing_of(states, actions, board_angle)
            return self._new_prompt(sid, "drawn", "your drawing (as drawn)", drawing, demo, "samples")

    def add_strokes_prompt(self, sid: str, strokes, board_angle: float, seed: int = 0, label: str = "") -> Prompt:
        """A drawing (unit-square strokes, y up) demonstrated by the built-in demonstrator at `board_angle`."""
        points = sum(len(s) for s in strokes)
        if points > 4 * MAX_POINTS:  # before any work: merging close points could not bring it under MAX_POINTS
            raise StudioError(
                f"strokes have {points} points; at most {MAX_POINTS} (after merging close ones)", "strokes", 422
            )
        try:
            drawing = bounded(Drawing.from_strokes("drawing", strokes, source="strokes"), "strokes")
        except DrawingError as err:
            raise StudioError(str(err), "strokes", 422) from None
        return self._demonstrated(sid, drawing, board_angle, seed, "strokes", "strokes", label or "your drawing")

    def add_file_prompt(self, sid: str, name: str, text: str, board_angle: float, seed: int = 0) -> Prompt:
        """The first drawing of an uploaded JSON stroke or SVG file's content (`name` only chooses the format
        and labels the prompt)."""
        suffix = Path(name).suffix.lower()
        if suffix not in (".json", ".svg"):
            raise StudioError(f"file name {name!r}: expected a .json or .svg drawing file", "name", 422)
        # Written under a name of the server's choosing; the client's name only labels the drawing and messages.
        stem = Path(name.replace("\\", "/")).stem[:64] or "drawing"
        session = self.session(sid)
        with self._preparing(sid):
            session.folder.mkdir(parents=True, exist_ok=True)
            upload = session.folder / f"upload-{secrets.token_hex(8)}{suffix}"
            upload.write_text(text, encoding="utf-8")
            try:
                drawing = load_drawings([upload])[0]
            except Exception as err:  # noqa: BLE001 - any parser failure is the file's fault: a 4xx with its message
                detail = str(err) if isinstance(err, DrawingError) else f"{type(err).__name__}: {err}"
                detail = detail.replace(str(upload), name).replace(upload.stem, stem)
                detail = detail if name in detail else f"{name}: cannot read it ({detail})"
                raise StudioError(detail, "text", 422) from None
            finally:
                upload.unlink(missing_ok=True)
        if drawing.id == upload.stem:  # an SVG drawing is named after its file
            drawing = Drawing(stem, drawing.strokes, name)
        return self._demonstrated(sid, drawing, board_angle, seed, f"file {name}", "text", Path(name).name[:200])

    def add_stored_prompt(self, sid: str, task: int, demo: int = 0) -> Prompt:
        """Demonstration `demo` of unseen drawing `task` (as ``bpp eval`` prompts it)."""
        store = self.human_store()
        if not 0 <= task < store.num_tasks:
            raise StudioError(f"task must be in [0, {store.num_tasks}), got {task}", "task", 422)
        episodes = store.task_episodes()[task]
        if not 0 <= demo < len(episodes):
            raise StudioError(f"demo must be in [0, {len(episodes)}), got {demo}", "demo", 422)
        with self._preparing(sid):
            episode = int(episodes[demo])
            steps = store.episode(episode, ("state", "action"))
            angle = float(store.column("board_angle")[episode])
            demo_obj = Demonstration(steps["state"], steps["action"].astype(np.float64), angle, 0.0)
            drawing = task_drawing(store, task)
            return self._new_prompt(sid, "stored", f"{drawing.id} (demo {demo})", drawing, demo_obj, "task")

    def _demonstrated(
        self, sid: str, drawing: Drawing, board_angle: float, seed: int, source: str, field: str, label: str
    ) -> Prompt:
        # The demonstrator plans a whole stroke before it counts steps, so a drawing whose ink could not be traced
        # within the prompt's steps even at its fastest is refused here, before seconds of planning.
        ink_px = drawing.ink_length * BOARD_SIZE
        fewest = int(ink_px / FASTEST_DEMO_STEP_PX) + 2 * len(drawing.strokes)
        if fewest > min(self.limits.max_prompt_steps, LAST_TRY_FACTOR * DemoConfig().max_steps):
            raise StudioError(
                f"its ink is {ink_px:.0f} px long: demonstrating it takes at least {fewest} steps, and a prompt has at "
                f"most {self.limits.max_prompt_steps}; use fewer or shorter strokes",
                field,
                422,
            )
        rng = np.random.default_rng(seed)
        start = rng.uniform(50.0, 450.0, size=2)
        with self._preparing(sid):
            try:
                demo = demonstrate(drawing, float(board_angle), start, rng, DemoConfig())
            except DrawingError as err:
                raise StudioError(str(err), field, 422) from None
            return self._new_prompt(sid, source, label, drawing, demo, field)

    def prompt(self, sid: str, pid: str) -> Prompt:
        prompt = self.session(sid).prompts.get(pid)  # None while it is still being written
        if prompt is None:
            raise StudioError(f"no prompt {pid!r} in this session", "prompt_id", 404)
        return prompt

    def delete_prompt(self, sid: str, pid: str) -> None:
        """Forget a prompt and delete its files (its finished rollouts keep what they need)."""
        session = self.session(sid)
        prompt = self.prompt(sid, pid)
        with self.lock:
            if any(r.running and r.prompt is prompt for r in session.rollouts.values()):
                raise StudioError("a rollout of this prompt is running; stop it first", "prompt_id", 409)
            session.prompts.pop(pid, None)
        shutil.rmtree(prompt.store.path, ignore_errors=True)

    def prompt_task_file(self, sid: str, pid: str) -> dict:
        """The prompt's drawing in the JSON stroke format, for ``bpp eval --files``."""
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
                for cached in session.folder.glob(f"rollout-{rid}.*"):
                    cached.unlink(missing_ok=True)
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
                # torch: imported when the command runs, not when the command line starts
                from bpp.checkpoint import Checkpoint

                self.models[checkpoint.id] = Checkpoint.load(checkpoint.path, use_ema=True).build_model()
            return self.models[checkpoint.id]

    def _run(self, rollout: Rollout) -> None:
        try:
            self._steps(rollout)
        except Exception as err:  # noqa: BLE001 - reported to the client, the studio goes on
            rollout.error = f"{type(err).__name__}: {err}"
            rollout.events.append(json.dumps({"type": "end", "status": "error", "error": rollout.error}))
            rollout.status = "error"
        finally:
            rollout.actions = np.asarray(rollout.actions, dtype=np.float64).reshape(-1, 3)
            with self.lock:
                if not rollout.readers:
                    rollout.drop_frames()

    def _wait_for_reader(self, rollout: Rollout) -> str | None:
        """Wait while the reader has ``frame_backlog`` frames unsent; returns why the rollout must end, if so."""
        while True:
            if rollout.stop.is_set():
                return "stopped"
            if time.monotonic() - rollout.last_read > self.limits.abandon_s:
                return "abandoned"
            if len(rollout.pending_frames) < self.limits.frame_backlog:
                return None
            time.sleep(0.02)

    def _steps(self, rollout: Rollout) -> None:
        # torch: imported when the command runs, not when the command line starts
        import torch

        from bpp.policies.agent import PolicyAgent

        if rollout.stop.is_set():  # stopped, or its reader left, before it began: no model to load for nobody
            rollout.end("stopped")
            return
        agent = PolicyAgent(self._model(rollout.checkpoint), record_attention=True)
        spec = agent.data_spec
        store = rollout.prompt.store
        agent.reset(task_context(store, 0, spec, get_benchmark(BENCHMARK).frames), rollout.seed)
        env = DrawEnv(
            image_size=spec.image_size if spec.image_keys else None,
            cameras=tuple(spec.image_keys),
            max_episode_steps=rollout.max_steps,
            action_frame=ACTION_FRAMES[spec.action_key],
            render_mode="rgb_array" if rollout.frames else None,
            render_size=rollout.frames or CANVAS_SIZE,
        )
        obs, _ = env.reset(
            seed=rollout.seed, options={"board_angle": rollout.board_angle, "target": rollout.prompt.target}
        )
        rollout.status = "running"
        start = {
            "type": "start",
            "board_angle": rollout.board_angle,
            "cursor": env.state[:2].tolist(),
            "prompt_steps": rollout.prompt.steps,
        }
        rollout.events.append(json.dumps(start))
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
            if len(agent.attention_log) > calls:
                calls = len(agent.attention_log)
                event["attention"] = [round(float(a), 4) for a in agent.attention_log[-1][0]]
            if rollout.frames:
                why = self._wait_for_reader(rollout)
                if why:
                    status = why
                    break
                rollout.pending_frames[len(rollout.events)] = _png_base64(env.render())
            rollout.events.append(json.dumps(event))
        rollout.end(status)

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
            "actions": np.asarray(rollout.actions, dtype=np.float64).tolist(),
            "limits": asdict(self.limits),
        }

    def animation(self, sid: str, rid: str, fmt: str, cancel: threading.Event | None = None, size: int = 256) -> Path:
        """The rollout as a GIF or MP4 (`fmt`), replayed from its actions (the physics is deterministic), rendered
        once per rollout and kept in the session's folder. One render per session and ``max_renders`` in all
        (refused, not queued); at most ``max_animation_frames`` frames; `cancel` set stops it (its client left)."""
        session = self.session(sid)
        rollout = self.rollout(sid, rid)
        if rollout.running:
            raise StudioError("the rollout is still running", "rollout_id", 409)
        path = session.folder / f"rollout-{rollout.id}.{fmt}"
        if path.is_file():
            return path
        with self.lock:
            if session.renders:
                raise StudioError("this session is already rendering an animation; wait for it", "rollout_id", 429)
            if not self._renders.acquire(blocking=False):
                raise StudioError("the studio is rendering other animations; try again shortly", "rollout_id", 429)
            session.renders += 1
        try:
            spec_frame = self._action_frame(rollout.checkpoint)
            partial = path.with_name(f".{path.stem}-{secrets.token_hex(4)}{path.suffix}")  # the suffix picks the format
            try:
                render_animation(rollout, spec_frame, partial, fmt, size, self.limits.max_animation_frames, cancel)
                partial.replace(path)
            except Cancelled:
                raise StudioError("the client left before the animation was ready", "rollout_id", 499) from None
            finally:
                partial.unlink(missing_ok=True)
        finally:
            with self.lock:
                session.renders -= 1
            self._renders.release()
        return path

    def _action_frame(self, checkpoint: CheckpointInfo) -> str:
        return ACTION_FRAMES[self._model(checkpoint).data_spec().action_key]


def _polylines(paths: list[np.ndarray]) -> list[list[list[float]]]:
    """Join consecutive per-step paths that continue each other into polylines, rounded to 0.1 px."""
    lines: list[list[list[float]]] = []
    for path in paths:
        points = np.round(np.asarray(path, dtype=np.float64), 1).tolist()
        if lines and lines[-1][-1] == points[0]:
            lines[-1].extend(points[1:])
        else:
            lines.append(points)
    return lines


def _png_base64(frame: np.ndarray) -> str:
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
