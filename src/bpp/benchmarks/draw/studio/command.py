"""``bpp studio`` (``bpp draw studio``): serve the studio on this machine."""

from __future__ import annotations

import gc
import os
import secrets
import signal
import socket
import tempfile
import threading
import tracemalloc
import webbrowser
from dataclasses import dataclass
from pathlib import Path

from bpp.benchmarks.draw.studio.engine import Studio
from bpp.benchmarks.draw.studio.memory import make_memory_releasable
from bpp.benchmarks.draw.studio.state import Limits, find_checkpoints
from bpp.errors import require_extra
from bpp.network import TOKEN_RULE, guarded_http, is_loopback, listen, strong_token, urls
from bpp.utils import check_fields


@dataclass(frozen=True)
class StudioCommand:
    """Prompt a policy yourself: a web page to draw a prompt and watch policies redraw it live, and its HTTP API.

    Binds 127.0.0.1 unless --host says otherwise; every API call needs the access token in the printed URL.
    """

    host: str = "127.0.0.1"
    """Address to listen on (0.0.0.0: every interface, e.g. for a phone on the same network)."""
    port: int = 8765
    """Port to listen on (0: any free one; the printed address names it)."""
    browser: bool = True
    """Open the page in a browser (--no-browser: just print its URL)."""
    runs: tuple[Path, ...] = (Path("runs"),)
    """Where to look for trained runs (run directories, or folders of them, two levels deep)."""
    token: str = ""
    """Access token ("": a new random one each start, the safer choice: a token on the command line is visible to
    other users of this machine in its process list)."""
    data_dir: Path | None = None
    """Where the unseen drawings are generated on first use (default: data/draw)."""
    threads: int = 1
    """torch threads per rollout (rollouts run side by side)."""
    max_rollouts: int = 8
    """Rollouts running at once, over all sessions (each session may run 2)."""

    def __post_init__(self):
        check_fields(
            self,
            ("port", 0 <= self.port <= 65535, "in [0, 65535]"),
            ("token", not self.token or strong_token(self.token), f"{TOKEN_RULE} (or empty: a random one)"),
            ("threads", self.threads >= 1, ">= 1"),
            ("max_rollouts", 1 <= self.max_rollouts <= 256, "in [1, 256]"),
        )


def studio(args: StudioCommand) -> None:
    make_memory_releasable()  # before the studio's threads allocate
    # torch: imported when the command runs, not when the command line starts
    import torch

    uvicorn = require_extra("uvicorn", "studio")
    require_extra("fastapi", "studio")
    # FastAPI: the studio extra
    from bpp.benchmarks.draw.studio.server import create_app

    main_thread = threading.current_thread() is threading.main_thread()
    if main_thread and os.environ.get("BPP_STUDIO_TRACEMALLOC"):
        _trace_allocations(os.environ["BPP_STUDIO_TRACEMALLOC"])
    if main_thread and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        # SIGTERM raises as Ctrl-C does, so that the private folder (users' prompts) is deleted either way; uvicorn
        # catches it while serving and raises it again once it has stopped.
        signal.signal(signal.SIGTERM, _interrupt)
    # Listen before printing anything: a busy port or an unknown host fails here, with nothing claimed, and
    # --port 0 learns the port the system chose.
    listener = listen(args.host, args.port)
    port = listener.getsockname()[1]
    torch.set_num_threads(args.threads)
    checkpoints = find_checkpoints(args.runs)
    token = args.token or secrets.token_urlsafe(24)
    try:
        with tempfile.TemporaryDirectory(prefix="bpp-studio-") as workdir:
            limits = Limits(max_rollouts=args.max_rollouts, max_sessions=max(64, 2 * args.max_rollouts))
            engine = Studio(checkpoints, Path(workdir), limits, data_dir=args.data_dir)
            names = {socket.gethostname(), socket.getfqdn(), f"{socket.gethostname()}.local", args.host}
            app = create_app(engine, token, hosts=names)
            urls = page_urls(args.host, port)
            if not checkpoints:
                where = ", ".join(map(str, args.runs))
                print(
                    f"[studio] no trained DrawAnything policy under {where}: run `bpp demo` first (or pass --runs DIR)"
                )
            else:
                print(f"[studio] {len(checkpoints)} checkpoint(s): " + "; ".join(c.label for c in checkpoints[:5]))
            if not is_loopback(args.host):
                print(
                    f"[studio] listening on {args.host}: anyone who can reach this machine and has the token can use "
                    "it; the page is plain HTTP, so the token crosses the network readable by anyone on the way: use "
                    "it only on a network you trust (or reach a loopback studio through `ssh -L`)"
                )
            for url in urls:
                print(f"[studio] open {url}#token={token}")
            print("[studio] API token (Authorization: Bearer ...): " + token)
            if args.browser:
                threading.Timer(1.0, webbrowser.open, (f"{urls[-1]}#token={token}",)).start()
            try:
                uvicorn.Server(server_config(app, limits)).run(sockets=[listener])
            finally:
                engine.close()
    finally:
        listener.close()


def server_config(app, limits: Limits, **where):
    """uvicorn's configuration for a studio `app`: every connection guarded before any route or token is read
    (:func:`bpp.network.guarded_http`), 256 connections and requests at once in all (503 beyond), idle connections
    closed after 5 s. `where`: uvicorn's host and port, where it opens the socket itself."""
    uvicorn = require_extra("uvicorn", "studio")
    return uvicorn.Config(
        app,
        http=guarded_http(limits.header_timeout_s, limits.max_connections_per_client),
        log_level="warning",
        limit_concurrency=256,
        timeout_keep_alive=5,
        timeout_graceful_shutdown=5,
        **where,
    )


def _trace_allocations(path: str) -> None:
    """A debugging aid, set by the environment variable BPP_STUDIO_TRACEMALLOC=FILE: on each SIGUSR1, write a
    tracemalloc snapshot of Python's live allocations to FILE. The first signal starts tracing (10 frames; the
    studio runs several times slower from then on), so a snapshot holds what was allocated since then and is still
    alive (``bench/studio_abuse.py --tracemalloc`` compares them between rounds of abuse)."""

    def dump(_signum, _frame) -> None:
        if not tracemalloc.is_tracing():
            tracemalloc.start(10)
        gc.collect()
        partial = f"{path}.partial"
        tracemalloc.take_snapshot().dump(partial)
        os.replace(partial, path)  # whole or absent: the reader waits for it to appear

    signal.signal(signal.SIGUSR1, dump)


def _interrupt(signum: int, _frame) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


def page_urls(host: str, port: int) -> list[str]:
    """Addresses of the page (without the token): for a wildcard host, this machine's network addresses (what a
    phone opens) and then loopback (what this machine opens); else the host itself."""
    return urls("http", host, port, "/")
