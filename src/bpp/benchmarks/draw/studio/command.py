"""``bpp studio`` (``bpp draw studio``): serve the studio on this machine."""

from __future__ import annotations

import ipaddress
import secrets
import tempfile
import threading
import webbrowser
from dataclasses import dataclass
from pathlib import Path

from bpp.utils import check_fields


@dataclass(frozen=True)
class StudioCommand:
    """Prompt a policy yourself: a web page to draw a prompt and watch policies redraw it live, and its HTTP API.

    Binds 127.0.0.1 unless --host says otherwise; every API call needs the access token in the printed URL.
    """

    host: str = "127.0.0.1"
    """Address to listen on (0.0.0.0: every interface, e.g. for a phone on the same network)."""
    port: int = 8765
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
            ("token", not self.token or len(self.token) >= 16, "at least 16 characters (or empty: a random one)"),
            ("threads", self.threads >= 1, ">= 1"),
            ("max_rollouts", 1 <= self.max_rollouts <= 256, "in [1, 256]"),
        )


def studio(args: StudioCommand) -> None:
    import torch

    from bpp.errors import require_extra

    uvicorn = require_extra("uvicorn", "studio")
    require_extra("fastapi", "studio")
    from bpp.benchmarks.draw.studio.engine import Limits, Studio, find_checkpoints
    from bpp.benchmarks.draw.studio.server import create_app

    torch.set_num_threads(args.threads)
    checkpoints = find_checkpoints(args.runs)
    token = args.token or secrets.token_urlsafe(24)
    with tempfile.TemporaryDirectory(prefix="bpp-studio-") as workdir:
        limits = Limits(max_rollouts=args.max_rollouts, max_sessions=max(64, 2 * args.max_rollouts))
        engine = Studio(checkpoints, Path(workdir), limits, data_dir=args.data_dir)
        app = create_app(engine, token)
        shown = "127.0.0.1" if args.host in ("0.0.0.0", "::") else args.host
        url = f"http://{shown}:{args.port}/?token={token}"
        if not checkpoints:
            where = ", ".join(map(str, args.runs))
            print(f"[studio] no trained DrawAnything policy under {where}: run `bpp demo` first (or pass --runs DIR)")
        else:
            print(f"[studio] {len(checkpoints)} checkpoint(s): " + "; ".join(c.label for c in checkpoints[:5]))
        if not _loopback(args.host):
            print(f"[studio] listening on {args.host}: anyone who can reach this machine and has the token can use it")
        print(f"[studio] open {url}")
        print("[studio] API token (Authorization: Bearer ...): " + token)
        if args.browser:
            threading.Timer(1.0, webbrowser.open, (url,)).start()
        try:
            uvicorn.run(app, host=args.host, port=args.port, log_level="warning")
        finally:
            engine.close()


def _loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"
