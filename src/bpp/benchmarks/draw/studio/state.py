"""What a studio holds: its limits, its sessions, their prompts and rollouts, and the checkpoints it serves; the
errors it answers with (:class:`StudioError`: a message, the field at fault and an HTTP status)."""

from __future__ import annotations

import hashlib
import json
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bpp.data.store import EpisodeStore

BENCHMARK = "drawanything"


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
    max_sessions_per_client: int = 16
    """Sessions one client address may hold, so that one client cannot take every place: its next one replaces its
    own least valuable one (:meth:`Studio.new_session`)."""
    max_prompt_jobs: int = 2
    """Prompts prepared at once in the whole studio (one per session)."""
    prompt_wait_s: float = 30.0
    """How long a prompt waits for one of those places (then 429); waiting prompts are served address by address,
    the least recently served first, one waiting per address (:class:`FairSlots`)."""
    max_waiting_prompts: int = 8
    """Prompts waiting at once in the whole studio (more are refused at once, 429)."""
    max_streams_per_session: int = 4
    max_streams: int = 64
    """Event streams open at once in the whole studio."""
    frame_backlog: int = 32
    """Rendered frames a rollout keeps for its reader; with that many unsent it waits for the reader."""
    max_renders: int = 2
    """Animations (GIF/MP4) rendered at once in the whole studio (one per session)."""
    max_animation_frames: int = 200
    """An animation shows at most this many frames (a longer rollout shows every k-th step, at the same pace)."""
    body_timeout_s: float = 10.0
    """A request body must arrive within this many seconds."""
    header_timeout_s: float = 10.0
    """A request's headers must arrive within this many seconds of the connection opening (or of its last answer)."""
    max_connections_per_client: int = 32
    """Connections one client address may hold open at once (a browser opens about 6 per page)."""


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
    ink: list = field(default_factory=list, repr=False)
    """What the recorded demonstration inked: canvas polylines [[x, y], ...] (px, 0.1 px), as the page shows it."""
    target: list = field(default_factory=list, repr=False)
    """The Chamfer target (the ink, upright), loaded once: rollouts and animations need it after a deletion."""

    def public(self, ink: bool = False) -> dict:
        out = {
            "id": self.id,
            "source": self.source,
            "label": self.label,
            "board_angle": self.board_angle,
            "steps": self.steps,
        }
        return {**out, "ink": self.ink} if ink else out


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
    events: list[str] = field(default_factory=list)
    """Every event as JSON text (a dict per event would take several times the memory)."""
    pending_frames: dict[int, str] = field(default_factory=dict)
    """Frames of events not yet sent, by event index: a frame is sent once, live, then forgotten."""
    readers: int = 0
    """Event streams open on it."""
    status: str = "starting"
    """starting, running, done, stopped (asked to), abandoned (nobody read it), error."""
    error: str = ""
    actions: list = field(default_factory=list)
    """Actions taken, as [x, y, pen] lists while running, as a (T, 3) float64 array once finished."""
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

    def end(self, status: str) -> None:
        """Append the end event (its score and steps) and take `status`."""
        end = {
            "type": "end",
            "status": status,
            "best_chamfer": self.public()["best_chamfer"],
            "steps": len(self.actions),
        }
        self.events.append(json.dumps(end))
        self.status = status  # after the end event: a stream that sees the rollout finished has it to send

    def drop_frames(self) -> None:
        """Forget the frames nobody has read (they are only for the live stream)."""
        self.pending_frames.clear()

    def event_text(self, index: int) -> str:
        """Event `index` as JSON, with its frame if it has not been sent yet (taking it: frames are sent once)."""
        text = self.events[index]
        frame = self.pending_frames.pop(index, None)
        return text if frame is None else f'{text[:-1]}, "frame": "{frame}"}}'

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
    client: str = ""
    """The client's address, for the per-client session limit."""
    streams: int = 0
    renders: int = 0
    preparing: bool = False
    """A prompt of this session is being prepared (one at a time)."""

    def busy(self) -> bool:
        """Work is under way: a running rollout, an open stream, a render or a prompt being prepared."""
        return bool(self.streams or self.renders or self.preparing or any(r.running for r in self.rollouts.values()))

    def worth(self) -> tuple[bool, float]:
        """What eviction weighs, least first: a session that holds nothing (no prompt, no rollout: a page opened and
        left, or a flood of new sessions) before one that holds work, then the least recently used."""
        return bool(self.prompts or self.rollouts), self.last_used


def find_checkpoints(roots) -> list[CheckpointInfo]:
    """DrawAnything runs (folders with ``checkpoints/last``, or checkpoint folders) under `roots`, newest first."""
    # torch: imported when the command runs, not when the command line starts
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


class FairSlots:
    """`slots` places shared fairly between client addresses: a request takes a free place at once if nobody waits;
    else it waits up to `timeout` seconds, and each freed place goes to the waiting address served least recently, so
    a client that sends many requests gets no more places than one that sends a few. Each address has at most one
    request waiting and at most `max_waiting` wait in all (the others are refused at once): waiting holds a server
    thread."""

    def __init__(self, slots: int, max_waiting: int):
        self.free, self.max_waiting = slots, max_waiting
        self.cond = threading.Condition()
        self.waiting: list[tuple[str, object]] = []
        self.served: dict[str, float] = {}

    def acquire(self, client: str, timeout: float) -> bool:
        """Take a place for `client` (an address); False if none came within `timeout` or it may not wait."""
        with self.cond:
            if self.free and not self.waiting:
                return self._take(client)
            if len(self.waiting) >= self.max_waiting or any(c == client for c, _ in self.waiting):
                return False
            ticket = (client, object())
            self.waiting.append(ticket)
            deadline = time.monotonic() + timeout
            try:
                while True:
                    if self.free and min(self.waiting, key=self._rank) is ticket:
                        self.waiting.remove(ticket)
                        return self._take(client)
                    left = deadline - time.monotonic()
                    if left <= 0:
                        self.waiting.remove(ticket)
                        return False
                    self.cond.wait(left)
            finally:
                self.cond.notify_all()  # the next in line may go now

    def release(self) -> None:
        with self.cond:
            self.free += 1
            self.cond.notify_all()

    def _take(self, client: str) -> bool:
        self.free -= 1
        self.served[client] = time.monotonic()
        if len(self.served) > 4096:  # forget the longest-served addresses; they rank as new again
            for old in sorted(self.served, key=self.served.get)[:2048]:
                del self.served[old]
        return True

    def _rank(self, ticket: tuple[str, object]) -> float:
        return self.served.get(ticket[0], -math.inf)
