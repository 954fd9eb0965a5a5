"""``bpp serve RUN``: build a policy server from a checkpoint and a prompt library, and run it."""

from __future__ import annotations

import asyncio
import logging
import os
import signal
from dataclasses import dataclass
from pathlib import Path

import tyro

from bpp.errors import UserError, require_extra
from bpp.utils import check_fields, resolve_device

TOKEN_ENV = "BPP_SERVE_TOKEN"


@dataclass(frozen=True)
class Serve:
    """Serve a checkpoint to robots over openpi's websocket protocol (openpi's WebsocketClientPolicy connects
    unchanged); clients pick behavior prompts from a prompt library by id, or upload their own.

    Examples:
      bpp serve runs/bpp_cpu --prompts human                 (a named task set of the run's benchmark; loopback)
      BPP_SERVE_TOKEN=secret bpp serve runs/bpp --prompts data/heldout.zarr --host 0.0.0.0
    """

    run: tyro.conf.Positional[Path]
    """Run directory or checkpoint folder."""
    prompts: str = "train"
    """The prompt library: train (the checkpoint's training store), a named task set of its benchmark (e.g. human),
    or any store path of the same benchmark."""
    host: str = "127.0.0.1"
    """Interface to listen on; anything but loopback requires a token."""
    port: int = 8000
    token: str = ""
    """Required of every client (``Authorization: Api-Key TOKEN``, openpi's api_key); default ${BPP_SERVE_TOKEN}.
    Prefer the variable: a flag is visible to other users in the process list."""
    device: str = "cpu"
    n_action_steps: int = 0
    """The Ta clients are told to execute per request (0: the checkpoint's)."""
    inference_steps: int = 0
    """Denoising steps per inference for diffusion decoders (0: the checkpoint's own)."""
    max_message_mb: float = 64.0
    """Largest request accepted (an uploaded demonstration with its frames must fit)."""
    max_clients: int = 64
    max_batch: int = 32
    """Concurrent requests answered by one batched inference call."""
    batch_wait_ms: float = 0.0
    """Time a request waits for others to share its batch (0: it joins those already waiting)."""
    data_dir: Path | None = None
    """Where a named task set is generated on first use (default: the benchmark's folder)."""

    def __post_init__(self):
        check_fields(
            self,
            ("port", 0 <= self.port < 65536, "in [0, 65535] (0: any free port)"),
            ("max_message_mb", self.max_message_mb > 0, "> 0"),
            ("max_clients", self.max_clients >= 1, ">= 1"),
            ("max_batch", self.max_batch >= 1, ">= 1"),
            ("batch_wait_ms", self.batch_wait_ms >= 0, ">= 0"),
            ("n_action_steps", self.n_action_steps >= 0, ">= 0 (0: the checkpoint's)"),
            ("inference_steps", self.inference_steps >= 0, ">= 0 (0: the checkpoint's)"),
        )


def build_server(
    run: str | Path,
    prompts: str = "train",
    *,
    token: str = "",
    device: str = "cpu",
    n_action_steps: int = 0,
    inference_steps: int = 0,
    limits=None,
    data_dir: Path | None = None,
):
    """A :class:`~bpp.serve.server.PolicyServer` for checkpoint `run`, offering the prompts of task set `prompts`."""
    require_extra("websockets", "serve")
    require_extra("msgpack", "serve")
    from bpp.checkpoint import Checkpoint
    from bpp.evaluation.evaluate import resolve_tasks
    from bpp.serve.prompts import PromptLibrary
    from bpp.serve.server import PolicyServer, ServerLimits

    device = resolve_device(device)  # before the checkpoint: a bad --device is the first thing said
    ckpt = Checkpoint.load(run, use_ema=True)
    model = ckpt.build_model(device)
    if inference_steps:
        model.set_inference_steps(inference_steps)
    benchmark, task_set, _ = resolve_tasks(prompts, ckpt, data_dir=data_dir)
    store = task_set.store
    library = PromptLibrary(model.data_spec(), model.validate_context, store, benchmark.frames)
    control_hz = store.config.get("fps") or getattr(benchmark, "control_hz", None)
    info = {
        "method": ckpt.method,
        "benchmark": benchmark.name,
        "checkpoint": str(ckpt.path),
        "train_step": ckpt.step,
        "weights_sha256": ckpt.weights_sha256,
        "control_hz": control_hz,
    }
    return PolicyServer(model, library, info, token, limits or ServerLimits(), device, n_action_steps or None)


def serve(args: Serve) -> None:
    from bpp.serve.server import ServerLimits, is_loopback

    token = args.token or os.environ.get(TOKEN_ENV, "")
    if not is_loopback(args.host) and not token:
        raise UserError(
            f"--host {args.host} exposes the policy beyond this machine: set a token (${TOKEN_ENV}, or --token) "
            "that every client must send, or serve on 127.0.0.1"
        )
    limits = ServerLimits(
        max_message_bytes=int(args.max_message_mb * 2**20),
        max_clients=args.max_clients,
        max_batch=args.max_batch,
        batch_wait_s=args.batch_wait_ms / 1e3,
    )
    server = build_server(
        args.run,
        args.prompts,
        token=token,
        device=args.device,
        n_action_steps=args.n_action_steps,
        inference_steps=args.inference_steps,
        limits=limits,
        data_dir=args.data_dir,
    )
    logging.basicConfig(level=logging.INFO, format="[serve] %(message)s")
    meta = server.metadata()
    lib = meta["prompts"]

    def ready(port: int) -> None:
        print(
            f"[serve] {meta['method']} @ step {meta['train_step']} on ws://{args.host}:{port} "
            f"({'token required' if token else 'no token: loopback only'}); prompts: {lib['episodes']} "
            f"demonstrations of {lib['tasks_total']} tasks in {lib['store']}; Ctrl-C stops",
            flush=True,
        )

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        await server.serve(args.host, args.port, ready, stop)

    try:
        asyncio.run(main())
    finally:
        server.close()
    print(f"[serve] stopped after {server.served} requests")
