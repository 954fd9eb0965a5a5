"""The studio's memory under an abusive token holder: before, during and after (the hardening issue).

    python bench/studio_abuse.py [--run runs/demo-bpp] [--seconds 40] [--rounds 3] [--tracemalloc]

Starts ``bpp studio --port 0`` in a subprocess (on a trained run: --run, else a 2-step debug run trained here) and
warms it up as ordinary users would, once along every path the abuse takes: 8 rollouts at once (two of 1000 steps), a
rollout's 256 px frames read to the end and its events read again, a GIF and an MP4, a download left before its render
ends, a drawing too long for a prompt, a request body cut off. Their sessions end, and 15 s later the server's
resident memory (VmRSS) is the baseline. Then --rounds rounds against the same server. In each, an owner's session
runs two new 1000-step rollouts, and then, for --seconds, abusive clients all at once: a flood of new sessions from
one address (a new loopback address each round); prompts uploaded without pause from three other addresses, four
sessions each; 40 connections that send half a request's headers and then nothing, reopened when closed, from another
address; rollouts streaming 256 px frames that nobody reads; event streams resumed past the end; GIF and MP4 downloads
of the owner's two rollouts, half of them dropped after 0.3 s; drawings too long to demonstrate; request bodies that
never arrive. Meanwhile one ordinary user keeps drawing and running rollouts: its refusals (each answered 429, then
retried after 0.5 s) and its rollouts are counted. Then the abusers end their sessions, the owner's too (the flood
just leaves), and the memory is measured 15 s and 45 s later (the abandon time is 30 s). Prints the memory of each
round (MiB) and what each kind of request got in each round.

--tracemalloc runs the server with BPP_STUDIO_TRACEMALLOC: Python's allocations are traced from the baseline on
(the server runs several times slower, and its memory includes the traces), and after each round the source lines
whose live allocations grew most since the round before are printed.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import tracemalloc
from collections import Counter
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).parent))
from bpp.benchmarks.draw.studio.client import StudioClient, StudioClientError  # noqa: E402
from studio_load import debug_run  # noqa: E402

TOKEN = "abuse-test-token-0123456789"
TRIANGLE = [[[0.2, 0.2], [0.8, 0.2], [0.5, 0.8], [0.2, 0.2]]]
ZIGZAG = [[[i / 3000, 0.2 + 0.5 * (i % 2)] for i in range(3000)]]
"""A drawing too long to demonstrate within a prompt's steps."""
SLOW_HEAD = f"POST /api/prompts HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {TOKEN}\r\n"
"""A request whose body never arrives (after the head, one byte)."""


def retried(call, tries: int = 100):
    """`call()`, retried while the studio answers 429 (busy: refusing rather than queueing is its job)."""
    for _ in range(tries - 1):
        try:
            return call()
        except StudioClientError as err:
            if err.status != 429:
                raise
            time.sleep(0.2)
    return call()


def rss_mib(pid: int, field: str = "VmRSS") -> float:
    """The process's resident memory (MiB): VmRSS, or its part RssAnon (heap, stacks) or RssFile (mapped files)."""
    text = Path(f"/proc/{pid}/status").read_text()
    return int(re.search(rf"{field}:\s+(\d+)", text).group(1)) / 1024


class Sampler(threading.Thread):
    """VmRSS every 0.2 s; `peak` since the last `reset`."""

    def __init__(self, pid: int):
        super().__init__(daemon=True)
        self.pid, self.peak, self.done = pid, 0.0, threading.Event()

    def run(self):
        while not self.done.is_set():
            self.peak = max(self.peak, rss_mib(self.pid))
            time.sleep(0.2)

    def reset(self) -> None:
        self.peak = rss_mib(self.pid)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, default=None, help="a trained run (default: a debug run trained here)")
    parser.add_argument("--seconds", type=float, default=40.0, help="abuse per round")
    parser.add_argument("--rounds", type=int, default=1, help="rounds of abuse against the same server")
    parser.add_argument("--tracemalloc", action="store_true", help="diff the server's Python allocations per round")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="studio-abuse-") as tmp:
        runs = args.run if args.run else debug_run(Path(tmp))
        command = [sys.executable, "-m", "bpp.cli", "studio", "--no-browser", "--port", "0", "--token", TOKEN]
        command += ["--runs", str(runs), "--data-dir", str(Path(tmp) / "data")]
        env = dict(os.environ)
        snapshots = Path(tmp) / "tracemalloc.snapshot" if args.tracemalloc else None
        if snapshots:
            env["BPP_STUDIO_TRACEMALLOC"] = str(snapshots)
        server = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
        try:
            url = None
            while url is None:
                line = server.stdout.readline()
                if not line:
                    raise SystemExit("the studio did not start")
                found = re.search(r"open (http://[^/]+)/", line)
                url = found.group(1) if found else None
            report(url, server.pid, args.seconds, args.rounds, snapshots)
        finally:
            server.terminate()
            server.wait(timeout=60)


def thread_count(pid: int) -> int:
    return int(re.search(r"Threads:\s+(\d+)", Path(f"/proc/{pid}/status").read_text()).group(1))


def snapshot(pid: int, path: Path) -> tracemalloc.Snapshot:
    """The server's tracemalloc snapshot (it writes one on SIGUSR1)."""
    path.unlink(missing_ok=True)
    os.kill(pid, signal.SIGUSR1)
    deadline = time.time() + 300
    while not path.exists():
        if time.time() > deadline:
            raise SystemExit("the studio wrote no tracemalloc snapshot (BPP_STUDIO_TRACEMALLOC)")
        time.sleep(0.2)
    return tracemalloc.Snapshot.load(str(path))


def print_growth(before: tracemalloc.Snapshot, after: tracemalloc.Snapshot, what: str) -> None:
    total = sum(s.size for s in after.statistics("filename")) - sum(s.size for s in before.statistics("filename"))
    print(f"traced Python allocations {what}: {total / 2**20:+.2f} MiB; the lines that grew most:")
    for stat in after.compare_to(before, "lineno")[:12]:
        frame = stat.traceback[0]
        where = f"{'/'.join(Path(frame.filename).parts[-3:])}:{frame.lineno}"
        print(f"  {stat.size_diff / 2**10:+9.1f} KiB {stat.count_diff:+7d} blocks  {where}")
    top = after.compare_to(before, "traceback")[:3]
    for stat in top:
        if stat.size_diff > 256 << 10:
            print(f"  traceback of {stat.size_diff / 2**10:+.1f} KiB:")
            for line in stat.traceback.format(most_recent_first=True)[:20]:
                print(f"    {line}")


def long_rollouts(owner: StudioClient, checkpoint: str) -> list[str]:
    """Two new 1000-step rollouts of `owner`'s session, run at once; returns their ids."""
    ends: list[str] = []

    def one() -> None:
        prompt = retried(lambda: owner.prompt_strokes(TRIANGLE))["id"]
        ends.append(retried(lambda: owner.run(prompt, checkpoint, max_steps=1000))["id"])

    runners = [threading.Thread(target=one) for _ in range(2)]
    for t in runners:
        t.start()
    for t in runners:
        t.join()
    return ends


def report(url: str, pid: int, seconds: float, rounds: int, snapshots: Path | None) -> None:
    sampler = Sampler(pid)
    sampler.start()
    start = rss_mib(pid)
    # Warm up as ordinary users at the studio's full concurrency (its thread pools grow with it, abuse or not):
    # 8 rollouts at once, two of them of 1000 steps.
    owner = StudioClient(url, TOKEN)
    checkpoint = owner.checkpoints()[0]["id"]
    users = [StudioClient(url, TOKEN) for _ in range(3)]

    def warm(c: StudioClient, steps: int) -> None:
        retried(lambda: c.run(retried(lambda: c.prompt_strokes(TRIANGLE))["id"], checkpoint, max_steps=steps))

    warmers = [threading.Thread(target=warm, args=(u, 200)) for u in users for _ in range(2)]
    for t in warmers:
        t.start()
    long_rollouts(owner, checkpoint)
    for t in warmers:
        t.join()
    # Then once each path the abuse takes, as ordinary use does: a rollout's 256 px frames read to the end, a
    # finished rollout's events read again (a reconnecting page), a GIF and an MP4 downloaded, a download left
    # before its render ended, a drawing too long for a prompt, a request body cut off by a network stall.
    user = users[0]
    framed = user.run(user.prompt_strokes(TRIANGLE)["id"], checkpoint, max_steps=200, frames=256)["id"]
    list(user.events(framed))
    for fmt in ("gif", "mp4"):
        done = user.run(user.prompt_strokes(TRIANGLE)["id"], checkpoint, max_steps=200)
        user.download(done["id"], Path(tempfile.gettempdir()) / f"studio-abuse-warmup.{fmt}").unlink()
    left = user.run(user.prompt_strokes(TRIANGLE)["id"], checkpoint, max_steps=1000)["id"]
    with contextlib.suppress(httpx.TimeoutException):
        user.http.get(f"/api/rollouts/{left}/episode.gif", timeout=0.3)
    with contextlib.suppress(StudioClientError):
        user.prompt_strokes(ZIGZAG)
    with socket.create_connection(url.removeprefix("http://").split(":"), timeout=30) as s:
        s.sendall(f"{SLOW_HEAD}Content-Length: 100\r\n\r\n{{".encode())
        s.recv(100)
    for u in [owner, *users]:
        u.close()
    time.sleep(15)  # as after each round: the studio gives freed memory back every 10 s
    baseline = rss_mib(pid)
    base_anon, base_file = rss_mib(pid, "RssAnon"), rss_mib(pid, "RssFile")
    rows = []
    outcomes: list[Counter] = []
    traced = snapshot(pid, snapshots) if snapshots else None
    first_traced = traced
    for r in range(1, rounds + 1):
        # The downloads are of two new 1000-step rollouts each round (an animation is rendered once, then cached),
        # run by their owner's session as ordinary use, before the abuse; the session ends with the abusers'.
        owner = StudioClient(url, TOKEN)
        long_ones = long_rollouts(owner, checkpoint)
        sampler.reset()
        got = abuse(url, checkpoint, owner, long_ones, seconds, flood_from=f"127.0.0.{1 + r}")
        owner.close()
        peak = sampler.peak
        time.sleep(15)
        after_15 = rss_mib(pid)
        time.sleep(30)  # the abandon time is 30 s from a rollout's last read
        anon, file = rss_mib(pid, "RssAnon") - base_anon, rss_mib(pid, "RssFile") - base_file
        rows.append((r, peak, after_15, rss_mib(pid), anon, file, thread_count(pid)))
        outcomes.append(got)
        print(f"round {r}: peak {peak:.0f} MiB, {after_15:.0f} MiB 15 s after, {rows[-1][3]:.0f} MiB 45 s after")
        if snapshots:
            now = snapshot(pid, snapshots)
            print_growth(traced, now, f"after round {r} against {'the baseline' if r == 1 else f'round {r - 1}'}")
            traced = now
    if snapshots and rounds > 1:
        print_growth(first_traced, traced, f"after round {rounds} against the baseline")
    sampler.done.set()
    print(f"abusive load for {seconds:.0f} s a round on {url}, {rounds} round(s) against the same server")
    print(f"started, nothing loaded: {start:.0f} MiB")
    print(f"baseline, after ordinary use of every path at full concurrency: {baseline:.0f} MiB")
    print(
        "| round | peak during the abuse | 15 s after the abusers ended or left | 45 s after | above the baseline |"
        " of which anonymous / mapped files | server threads |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for r, peak, after_15, after_45, anon, file, n in rows:
        print(
            f"| {r} | {peak:.0f} | {after_15:.0f} | {after_45:.0f} | {after_45 - baseline:+.0f} | {anon:+.0f} / "
            f"{file:+.0f} | {n} |"
        )
    print("what each kind of request got, per round:")
    for key in sorted(set().union(*outcomes)):
        print(f"  {key}: {', '.join(str(got[key]) for got in outcomes)}")


def abuse(url: str, checkpoint: str, owner: StudioClient, long_ones: list[str], seconds: float, flood_from: str):
    """One round of abuse, for `seconds`; returns what each kind of request got (status counts). The downloads are
    of `owner`'s rollouts `long_ones`, in its session; the flood of new sessions comes from address `flood_from`."""
    got: Counter = Counter()
    stop_at = time.time() + seconds
    lock = threading.Lock()

    def count(what: str, status) -> None:
        with lock:
            got[f"{what}: {status}"] += 1

    def sessions_flood():
        transport = httpx.HTTPTransport(local_address=flood_from)
        with httpx.Client(base_url=url, transport=transport) as http:
            while time.time() < stop_at:
                r = http.post("/api/session", headers={"Authorization": f"Bearer {TOKEN}", "Connection": "close"})
                count("new session", r.status_code)
                time.sleep(0.02)

    def unread_frames():
        with StudioClient(url, TOKEN) as c:
            prompt = retried(lambda: c.prompt_strokes(TRIANGLE))["id"]
            while time.time() < stop_at:
                try:
                    c.rollout(prompt, checkpoint, max_steps=1000, frames=256)
                    count("unread 256 px rollout", 200)
                except StudioClientError as err:
                    count("unread 256 px rollout", err.status)
                time.sleep(1.0)

    def past_the_end():
        with StudioClient(url, TOKEN) as c:
            rollout = retried(lambda: c.run(c.prompt_strokes(TRIANGLE)["id"], checkpoint, max_steps=5))["id"]
            while time.time() < stop_at:
                try:
                    r = c.http.get(f"/api/rollouts/{rollout}/events", params={"since": 10**6}, timeout=5)
                    count("stream resumed past the end", r.status_code)
                except httpx.TimeoutException:
                    count("stream resumed past the end", "never ended")

    def downloads(fmt: str, rollout: str, drop: bool):
        """The same rollout again and again: a dropped download is rendered anew each time (and stopped), a
        complete one is rendered once and then read from the cache."""
        headers = {"Authorization": f"Bearer {TOKEN}", "X-Studio-Session": owner.session}
        with httpx.Client(base_url=url, headers=headers) as http:
            while time.time() < stop_at:
                what = f"{fmt} download of a 1000-step rollout{' (dropped at 0.3 s)' if drop else ''}"
                try:
                    r = http.get(f"/api/rollouts/{rollout}/episode.{fmt}", timeout=0.3 if drop else 120)
                    count(what, r.status_code)
                except httpx.TimeoutException:
                    count(what, "dropped")

    def long_drawings():
        with StudioClient(url, TOKEN) as c:
            while time.time() < stop_at:
                t0 = time.perf_counter()
                try:
                    c.prompt_strokes(ZIGZAG)
                    count("zigzag prompt", 200)
                except StudioClientError as err:
                    count(f"zigzag prompt ({time.perf_counter() - t0:.1f} s)", err.status)

    def slow_bodies():
        while time.time() < stop_at:
            with socket.create_connection(url.removeprefix("http://").split(":"), timeout=30) as s:
                s.sendall(f"{SLOW_HEAD}Content-Length: 1000000\r\n\r\n{{".encode())
                status = s.recv(100).decode().split(" ")[1:2]
                count("body that never arrives", status[0] if status else "closed")

    def ordinary_user():  # at an address of its own, as another person's machine is
        with StudioClient(url, TOKEN, local_address="127.0.2.1") as c:
            while time.time() < stop_at:
                try:
                    prompt = c.prompt_strokes(TRIANGLE)["id"]
                    count("ordinary user's prompt", 200)
                except StudioClientError as err:
                    count(f"ordinary user's prompt ({err.detail.split(';')[0]})", err.status)
                    time.sleep(0.5)
                    continue
                while time.time() < stop_at:
                    try:
                        end = c.run(prompt, checkpoint, max_steps=50)
                        count("ordinary user's rollout", end["status"])
                        break
                    except StudioClientError as err:
                        count("ordinary user's rollout", err.status)
                        time.sleep(0.5)
                c._call("DELETE", f"/api/prompts/{prompt}")

    def prompt_flood(address: str):
        clients = [StudioClient(url, TOKEN, local_address=address) for _ in range(4)]
        try:
            while time.time() < stop_at:
                for c in clients:
                    try:
                        c._call("DELETE", f"/api/prompts/{c.prompt_strokes(TRIANGLE)['id']}")
                        count("prompt flood", 200)
                    except StudioClientError as err:
                        count("prompt flood", err.status)
        finally:
            for c in clients:
                c.close()

    def half_headers(address: str):
        host, port = url.removeprefix("http://").split(":")
        held: list[socket.socket] = []
        while time.time() < stop_at:
            for sock in list(held):
                try:
                    sock.recv(100)  # b"" (closed) or a 429: the server let it go
                except BlockingIOError:
                    continue  # still held open by the server
                except OSError:
                    pass
                held.remove(sock)
                sock.close()
                count("half-sent headers: connection closed by the server", "closed")
            while len(held) < 40 and time.time() < stop_at:
                sock = socket.socket()
                sock.bind((address, 0))
                sock.connect((host, int(port)))
                sock.sendall(b"GET /api/checkpoints HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Wait: ")
                sock.setblocking(False)
                held.append(sock)
                count("half-sent headers: connection opened", "opened")
            time.sleep(0.2)
        for sock in held:
            sock.close()

    workers = [sessions_flood, unread_frames, unread_frames, past_the_end, long_drawings, slow_bodies, ordinary_user]
    workers += [lambda a=a: prompt_flood(a) for a in ("127.0.1.3", "127.0.1.4", "127.0.1.5")]
    workers.append(lambda: half_headers("127.0.1.6"))
    a, b = long_ones
    workers += [lambda: downloads("gif", a, True), lambda: downloads("mp4", b, True)]
    workers += [lambda: downloads("gif", a, False), lambda: downloads("mp4", b, False)]
    threads = [threading.Thread(target=w, daemon=True) for w in workers]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=seconds + 180)
    return got


if __name__ == "__main__":
    main()
