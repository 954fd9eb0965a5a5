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
from bpp.network import TOKEN_RULE, WILDCARD_HOSTS, is_loopback, strong_token, urls
from bpp.serve.prompts import PromptLibrary
from bpp.utils import check_fields, resolve_device

TOKEN_ENV = "BPP_SERVE_TOKEN"


@dataclass(frozen=True)
class Serve:
    """Serve a checkpoint to robots over openpi's websocket protocol (openpi's WebsocketClientPolicy connects
    unchanged); clients pick behavior prompts from a prompt library by id, or upload their own.

    Examples:
      bpp serve runs/bpp_cpu --prompts human                 (a named task set of the run's benchmark; loopback)
      BPP_SERVE_TOKEN=$(openssl rand -hex 16) bpp serve runs/bpp --prompts data/heldout.zarr --host 0.0.0.0
    """

    run: tyro.conf.Positional[Path]
    """Run directory or checkpoint folder."""
    prompts: str = "train"
    """The prompt library: train (the checkpoint's training store), a named task set of its benchmark (e.g. human),
    or any store path of the same benchmark."""
    host: str = "127.0.0.1"
    """Interface to listen on (0.0.0.0: all of them); anything but loopback requires a token."""
    port: int = 8000
    token: str = ""
    """Required of every client (``Authorization: Api-Key TOKEN``, openpi's api_key); default ${BPP_SERVE_TOKEN}.
    Beyond loopback, at least 16 visible ASCII characters. Prefer the variable: a flag is visible to other users in
    the process list."""
    device: str = "cpu"
    n_action_steps: int = 0
    """The Ta clients are told to execute per request (0: the checkpoint's)."""
    inference_steps: int = 0
    """Denoising steps per inference for diffusion decoders (0: the checkpoint's own)."""
    max_message_mb: float = 64.0
    """Largest request accepted (an uploaded demonstration with its frames must fit)."""
    max_clients: int = 64
    max_uploads_per_client: int = 4
    """Uploaded prompts one connection holds; its oldest is let go when it uploads more."""
    max_upload_mb: float = 1024.0
    """All uploaded prompts held at once; an upload beyond it is refused until connections holding others close."""
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
            ("max_uploads_per_client", self.max_uploads_per_client >= 1, ">= 1"),
            ("max_upload_mb", self.max_upload_mb > 0, "> 0"),
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
    max_uploads_per_client: int = 4,
    max_upload_bytes: int = 2**30,
    data_dir: Path | None = None,
):
    """A :class:`~bpp.serve.server.PolicyServer` for checkpoint `run`, offering the prompts of task set `prompts`
    (and uploads, bounded as :class:`~bpp.serve.prompts.PromptLibrary` says)."""
    require_extra("websockets", "serve")
    require_extra("msgpack", "serve")
    # torch: imported when the command runs, not when the command line starts
    from bpp.checkpoint import Checkpoint
    from bpp.evaluation.evaluate import resolve_tasks
    from bpp.serve.server import PolicyServer, ServerLimits

    device = resolve_device(device)  # before the checkpoint: a bad --device is the first thing said
    ckpt = Checkpoint.load(run, use_ema=True)
    model = ckpt.build_model(device)
    if inference_steps:
        model.set_inference_steps(inference_steps)
    benchmark, task_set, _ = resolve_tasks(prompts, ckpt, data_dir=data_dir, flag="--prompts")
    store = task_set.store
    library = PromptLibrary(
        model.data_spec(), model.validate_context, store, benchmark.frames, max_uploads_per_client, max_upload_bytes
    )
    # the store's own rate (recorded data), else its benchmark's robot's
    control_hz = store.config.get("fps") or getattr(benchmark, "control_hz", None)
    info = {
        "method": ckpt.method,
        "benchmark": benchmark.name,
        "checkpoint": checkpoint_name(ckpt.path),
        "train_step": ckpt.step,
        "weights_sha256": ckpt.weights_sha256,
        "control_hz": control_hz,
    }
    return PolicyServer(model, library, info, token, limits or ServerLimits(), device, n_action_steps or None)


def checkpoint_name(path: Path) -> str:
    """A checkpoint folder as clients see it: ``<run>/<step folder>``, no path of the server's."""
    return f"{path.parent.parent.name}/{path.name}" if path.parent.name == "checkpoints" else path.name


def serve(args: Serve) -> None:
    # torch: imported when the command runs, not when the command line starts
    from bpp.serve.server import ServerLimits

    token = args.token or os.environ.get(TOKEN_ENV, "")
    if not is_loopback(args.host) and not token:
        raise UserError(
            f"--host {args.host} exposes the policy beyond this machine: set a token (${TOKEN_ENV}, or --token) "
            "that every client must send, or serve on 127.0.0.1"
        )
    if not is_loopback(args.host) and not strong_token(token):
        raise UserError(
            f"--host {args.host} exposes the policy beyond this machine: its token (${TOKEN_ENV} or --token) must "
            f"be {TOKEN_RULE}, e.g. $(openssl rand -hex 16)"
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
        max_uploads_per_client=args.max_uploads_per_client,
        max_upload_bytes=int(args.max_upload_mb * 2**20),
        data_dir=args.data_dir,
    )
    logging.basicConfig(level=logging.INFO, format="[serve] %(message)s")
    meta = server.metadata()
    lib = meta["prompts"]

    def ready(port: int) -> None:
        where = "all interfaces; " if args.host in WILDCARD_HOSTS else ""
        access = "token required" if token else "no token: loopback only"
        print(
            f"[serve] {meta['method']} @ step {meta['train_step']} on {', '.join(urls('ws', args.host, port))} "
            f"({where}{access}); prompts: {lib['episodes']} demonstrations of {lib['tasks_total']} tasks in "
            f"{server.library.store.path}; Ctrl-C stops",
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
