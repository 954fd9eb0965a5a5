"""``bpp iphumi prompt``: one phone recording -> the behavior prompt of a running policy server.

The recording is processed exactly as ``bpp iphumi process`` processes a demonstration (at the served model's
image size and control rate, the whole demonstration as one episode), then uploaded over the server's
authenticated websocket API (``{"upload": demonstration}``, :mod:`bpp.serve.server`). The server answers with the
prompt's handle; a robot client naming that handle, or ``upload:latest`` (the newest upload), runs it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from bpp.benchmarks.iphumi.pipeline import process_one
from bpp.benchmarks.iphumi.process import ProcessSettings
from bpp.errors import UserError
from bpp.serve.client import PolicyClient, ServerError
from bpp.serve.wire import pack


@dataclass
class HandOff:
    """What a prompt hand-off did and how long each part took (seconds)."""

    handle: str
    task: str
    steps: int
    upload_bytes: int
    process_s: float
    upload_s: float
    first_action_s: float | None = None
    """From the upload's reply to the first action of an episode prompted with it (None if not checked)."""
    first_action: np.ndarray | None = None


def demonstration_for(metadata: dict, episode: dict) -> dict:
    """A processed episode -> the upload a server with `metadata` takes: the observation keys it serves, its action
    key, the task's name as the instruction (the Language method's prompt)."""
    observed = metadata.get("observation", {})
    missing = sorted(set(observed) - set(episode["steps"]))
    if missing:
        raise UserError(
            f"the served policy observes {missing}, which an iPhUMI recording does not give (it gives "
            f"{sorted(episode['steps'])}); serve a model trained on an iPhUMI store"
        )
    action = metadata.get("action", {}).get("key", "action")
    obs = {key: np.ascontiguousarray(episode["steps"][key]) for key in observed}
    return {"obs": obs, "action": episode["steps"][action], "instruction": episode["task"]}


def hand_off(
    recording: Path,
    server: str,
    token: str | None = None,
    settings: ProcessSettings = ProcessSettings(),
    export: Path | None = None,
    check: bool = True,
) -> HandOff:
    """Process `recording` for the policy served at `server` and upload it as a prompt; with `check`, start one
    episode with it on this connection (one observation: the recording's first step) to time the first action."""
    try:
        client = PolicyClient(server, api_key=token)
    except OSError as err:
        raise UserError(f"cannot reach the policy server at {server} ({err})") from None
    except Exception as err:  # the websocket library's refusals (401 without the token, 503 when full)
        raise UserError(f"the policy server at {server} refused the connection ({err})") from None
    try:
        metadata = client.get_server_metadata()
        shapes = metadata.get("observation", {})
        images = [k for k, v in shapes.items() if len(v.get("shape", [])) == 3]
        size = int(shapes[images[0]]["shape"][0]) if images else settings.image_size
        cameras = tuple(sorted({k.removeprefix("arm1_").removeprefix("head_") for k in images})) or ("rgb",)
        fps = float(metadata.get("control_hz") or settings.fps)
        settings = replace(settings, image_size=size, cameras=cameras, fps=fps)
        t0 = time.perf_counter()
        episode = process_one(recording, settings, export)
        demo = demonstration_for(metadata, episode)
        message = pack({"upload": demo})
        limit = int(metadata.get("max_message_bytes", 0))
        if limit and len(message) > limit:
            raise UserError(
                f"{recording}: the prompt is {_size(len(message))}, over the {_size(limit)} a message to this "
                "server may have; record a shorter demonstration, or serve with a larger "
                "--max-message-mb"
            )
        t1 = time.perf_counter()
        try:
            reply = client.infer({"upload": demo})
        except ServerError as err:
            raise UserError(f"the server refused the prompt: {str(err).splitlines()[-1]}") from None
        t2 = time.perf_counter()
        result = HandOff(reply["prompt"], episode["task"], len(demo["action"]), len(message), t1 - t0, t2 - t1)
        if check:
            first = {key: value[0] for key, value in demo["obs"].items()}
            actions = client.infer({**first, "prompt": result.handle, "reset": True})
            result.first_action_s = time.perf_counter() - t2
            result.first_action = np.asarray(actions["actions"])[0]
        return result
    finally:
        client.close()


def _size(count: int) -> str:
    return f"{count / 2**20:.1f} MiB" if count >= 2**20 else f"{count / 1024:.0f} KiB"
