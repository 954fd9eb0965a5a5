"""A Python client of the studio's HTTP API (for scripts, other workstations, tests).

from bpp.benchmarks.draw.studio.client import StudioClient

studio = StudioClient("http://127.0.0.1:8765", token)        # the token `bpp studio` printed
checkpoint = studio.checkpoints()[0]["id"]
prompt = studio.prompt_file("house.svg", board_angle=0.3)     # or prompt_strokes, prompt_drawn, prompt_stored
end = studio.run(prompt["id"], checkpoint, board_angle=-0.4)  # streams the rollout to its end
print(end["best_chamfer"])
studio.download(end["id"], "rollout.gif")
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from pathlib import Path

import httpx


class StudioClientError(RuntimeError):
    """The studio refused a request: ``status`` (HTTP), ``detail`` and the ``field`` it names."""

    def __init__(self, status: int, detail: str, field: str = ""):
        super().__init__(f"{status}: {detail}")
        self.status, self.detail, self.field = status, detail, field


class StudioClient:
    """One session of a studio server."""

    def __init__(self, url: str, token: str, timeout: float = 120.0, local_address: str | None = None):
        """A session of the studio at `url`; `local_address` is the address to connect from (the studio counts
        sessions per client address)."""
        transport = httpx.HTTPTransport(local_address=local_address) if local_address else None
        self.http = httpx.Client(
            base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=timeout, transport=transport
        )
        self.session = self._call("POST", "/api/session")["session"]
        self.http.headers["X-Studio-Session"] = self.session

    def close(self) -> None:
        """End the session (the studio deletes its prompts and stops its rollouts) and the connection."""
        with contextlib.suppress(httpx.HTTPError):  # the studio may be gone already
            self.http.delete("/api/session")
        self.http.close()

    def __enter__(self) -> StudioClient:
        return self

    def __exit__(self, *_) -> None:
        self.close()

    def _call(self, method: str, path: str, body: dict | None = None, **params):
        response = self.http.request(method, path, json=body, params=params or None)
        _check(response)
        return response.json()

    # ------------------------------------------------------------------------------------------------ lists
    def checkpoints(self) -> list[dict]:
        return self._call("GET", "/api/checkpoints")

    def stored(self) -> list[dict]:
        return self._call("GET", "/api/stored")

    # ---------------------------------------------------------------------------------------------- prompts
    def prompt_drawn(self, samples, board_angle: float = 0.0) -> dict:
        """A demonstration as drawn: [x, y, pen] cursor targets in canvas px, one per 0.1 s."""
        return self._call("POST", "/api/prompts", {"kind": "drawn", "samples": samples, "board_angle": board_angle})

    def prompt_strokes(self, strokes, board_angle: float = 0.0, seed: int = 0) -> dict:
        """A drawing (unit-square strokes, y up), demonstrated by the built-in demonstrator."""
        body = {"kind": "strokes", "strokes": strokes, "board_angle": board_angle, "seed": seed}
        return self._call("POST", "/api/prompts", body)

    def prompt_file(self, path: str | Path, board_angle: float = 0.0, seed: int = 0) -> dict:
        """The first drawing of a local JSON stroke or SVG file (its content is sent, never its path)."""
        path = Path(path)
        body = {
            "kind": "file",
            "name": path.name,
            "text": path.read_text(encoding="utf-8"),
            "board_angle": board_angle,
            "seed": seed,
        }
        return self._call("POST", "/api/prompts", body)

    def prompt_stored(self, task: int, demo: int = 0) -> dict:
        return self._call("POST", "/api/prompts", {"kind": "stored", "task": task, "demo": demo})

    def task_file(self, prompt_id: str) -> dict:
        """The prompt as a task file for ``bpp eval --files``."""
        return self._call("GET", f"/api/prompts/{prompt_id}/task.json")

    # --------------------------------------------------------------------------------------------- rollouts
    def rollout(
        self,
        prompt_id: str,
        checkpoint_id: str,
        board_angle: float | None = None,
        seed: int = 0,
        max_steps: int = 400,
        frames: int = 0,
    ) -> dict:
        """Start a rollout (board_angle None: a random one; frames 64, 128 or 256: each step event carries the
        rendered frame as a base64 PNG); returns its status (``id``, ``status``, ...)."""
        body = {
            "prompt_id": prompt_id,
            "checkpoint_id": checkpoint_id,
            "board_angle": board_angle,
            "seed": seed,
            "max_steps": max_steps,
            "frames": frames,
        }
        return self._call("POST", "/api/rollouts", body)

    def events(self, rollout_id: str, since: int = 0) -> Iterator[dict]:
        """The rollout's events as they happen (start, step..., end); leaving early stops the rollout."""
        with self.http.stream("GET", f"/api/rollouts/{rollout_id}/events", params={"since": since}) as response:
            if response.status_code >= 400:
                response.read()
                _check(response)
            for line in response.iter_lines():
                if line.startswith("data: "):
                    yield json.loads(line[6:])

    def run(self, prompt_id: str, checkpoint_id: str, **kw) -> dict:
        """Start a rollout and follow it to the end; returns the end event with the rollout's ``id``."""
        rollout = self.rollout(prompt_id, checkpoint_id, **kw)
        end = {}
        for event in self.events(rollout["id"]):
            if event["type"] == "end":
                end = event
        return {**end, "id": rollout["id"]}

    def status(self, rollout_id: str) -> dict:
        return self._call("GET", f"/api/rollouts/{rollout_id}")

    def stop(self, rollout_id: str) -> dict:
        return self._call("DELETE", f"/api/rollouts/{rollout_id}")

    def episode(self, rollout_id: str) -> dict:
        return self._call("GET", f"/api/rollouts/{rollout_id}/episode.json")

    def download(self, rollout_id: str, path: str | Path) -> Path:
        """Save the rollout as ``.json``, ``.gif`` or ``.mp4`` (by `path`'s suffix)."""
        path = Path(path)
        response = self.http.get(f"/api/rollouts/{rollout_id}/episode{path.suffix.lower()}")
        _check(response)
        path.write_bytes(response.content)
        return path


def _check(response: httpx.Response) -> None:
    if response.status_code < 400:
        return
    try:
        data = response.json()
    except ValueError:
        data = {"detail": response.text}
    raise StudioClientError(response.status_code, str(data.get("detail")), str(data.get("field", "")))
