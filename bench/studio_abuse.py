"""The studio's memory under an abusive token holder: before, during and after (the hardening issue).

    python bench/studio_abuse.py [--run runs/demo-bpp] [--seconds 40]

Starts ``bpp studio --port 0`` in a subprocess (on a trained run: --run, else a 2-step debug run trained here),
warms it up like a normal user (one rollout, one GIF), and takes its resident memory (VmRSS) as the baseline.
Then, for --seconds, abusive clients all at once: a flood of new sessions from one address; rollouts streaming
256 px frames that nobody reads; event streams resumed past the end; GIF and MP4 downloads of 1000-step rollouts,
most dropped after 0.3 s; drawings too long to demonstrate; request bodies that never arrive. Meanwhile one
ordinary user keeps drawing and running rollouts, and must never be refused nor evicted. Then the abusers end their
sessions (or just leave), and after the abandon time the memory is measured again. Prints the memory at each
phase (MiB) and what the abusers got (status counts).
"""

from __future__ import annotations

import argparse
import re
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).parent))
from bpp.benchmarks.draw.studio.client import StudioClient, StudioClientError  # noqa: E402
from studio_load import debug_run  # noqa: E402

TOKEN = "abuse-test-token-0123456789"
TRIANGLE = [[[0.2, 0.2], [0.8, 0.2], [0.5, 0.8], [0.2, 0.2]]]


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


def rss_mib(pid: int) -> float:
    text = Path(f"/proc/{pid}/status").read_text()
    return int(re.search(r"VmRSS:\s+(\d+)", text).group(1)) / 1024


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
    parser.add_argument("--seconds", type=float, default=40.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="studio-abuse-") as tmp:
        runs = args.run if args.run else debug_run(Path(tmp))
        command = [sys.executable, "-m", "bpp.cli", "studio", "--no-browser", "--port", "0", "--token", TOKEN]
        command += ["--runs", str(runs), "--data-dir", str(Path(tmp) / "data")]
        server = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        try:
            url = None
            while url is None:
                line = server.stdout.readline()
                if not line:
                    raise SystemExit("the studio did not start")
                found = re.search(r"open (http://[^/]+)/", line)
                url = found.group(1) if found else None
            report(url, server.pid, args.seconds)
        finally:
            server.terminate()
            server.wait(timeout=60)


def report(url: str, pid: int, seconds: float) -> None:
    sampler = Sampler(pid)
    sampler.start()
    start = rss_mib(pid)
    # Warm up as ordinary users at the studio's full concurrency (its thread pools and allocator arenas grow with
    # it, abuse or not): 8 rollouts at once, then a GIF and an MP4. Two 1000-step rollouts are kept for downloads.
    keeper = StudioClient(url, TOKEN)
    checkpoint = keeper.checkpoints()[0]["id"]
    users = [StudioClient(url, TOKEN) for _ in range(3)]
    long_ones: list[str] = []

    def warm(c: StudioClient, steps: int, keep: bool) -> None:
        end = retried(lambda: c.run(retried(lambda: c.prompt_strokes(TRIANGLE))["id"], checkpoint, max_steps=steps))
        if keep:
            long_ones.append(end["id"])

    jobs = [(keeper, 1000, True), (keeper, 1000, True)] + [(u, 200, False) for u in users for _ in range(2)]
    warmers = [threading.Thread(target=warm, args=job) for job in jobs]
    for t in warmers:
        t.start()
    for t in warmers:
        t.join()
    for fmt in ("gif", "mp4"):
        done = users[0].run(users[0].prompt_strokes(TRIANGLE)["id"], checkpoint, max_steps=200)
        users[0].download(done["id"], Path(tempfile.gettempdir()) / f"studio-abuse-warmup.{fmt}").unlink()
    for u in users:
        u.close()
    time.sleep(5)
    baseline = rss_mib(pid)
    sampler.reset()
    got: Counter = Counter()
    stop_at = time.time() + seconds
    lock = threading.Lock()

    def count(what: str, status) -> None:
        with lock:
            got[f"{what}: {status}"] += 1

    def sessions_flood():
        while time.time() < stop_at:
            r = httpx.post(f"{url}/api/session", headers={"Authorization": f"Bearer {TOKEN}"})
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
        headers = {"Authorization": f"Bearer {TOKEN}", "X-Studio-Session": keeper.session}
        with httpx.Client(base_url=url, headers=headers) as http:
            while time.time() < stop_at:
                what = f"{fmt} download of a 1000-step rollout{' (dropped at 0.3 s)' if drop else ''}"
                try:
                    r = http.get(f"/api/rollouts/{rollout}/episode.{fmt}", timeout=0.3 if drop else 120)
                    count(what, r.status_code)
                except httpx.TimeoutException:
                    count(what, "dropped")

    def long_drawings():
        zigzag = [[[i / 3000, 0.2 + 0.5 * (i % 2)] for i in range(3000)]]
        with StudioClient(url, TOKEN) as c:
            while time.time() < stop_at:
                t0 = time.perf_counter()
                try:
                    c.prompt_strokes(zigzag)
                    count("zigzag prompt", 200)
                except StudioClientError as err:
                    count(f"zigzag prompt ({time.perf_counter() - t0:.1f} s)", err.status)

    def slow_bodies():
        while time.time() < stop_at:
            with socket.create_connection(url.removeprefix("http://").split(":"), timeout=30) as s:
                head = f"POST /api/prompts HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {TOKEN}\r\n"
                s.sendall((head + "Content-Length: 1000000\r\n\r\n{").encode())
                status = s.recv(100).decode().split(" ")[1:2]
                count("body that never arrives", status[0] if status else "closed")

    def ordinary_user():
        with StudioClient(url, TOKEN) as c:
            while time.time() < stop_at:
                try:
                    end = retried(lambda: c.run(c.prompt_strokes(TRIANGLE)["id"], checkpoint, max_steps=50))
                    count("ordinary user's rollout", end["status"])
                    c._call("DELETE", f"/api/prompts/{c.episode(end['id'])['prompt']['id']}")
                except StudioClientError as err:
                    count("ordinary user's rollout", err.status)
                    time.sleep(0.5)

    workers = [sessions_flood, unread_frames, unread_frames, past_the_end, long_drawings, slow_bodies, ordinary_user]
    a, b = long_ones
    workers += [lambda: downloads("gif", a, True), lambda: downloads("mp4", b, True)]
    workers += [lambda: downloads("gif", a, False), lambda: downloads("mp4", b, False)]
    threads = [threading.Thread(target=w, daemon=True) for w in workers]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=seconds + 180)
    during = sampler.peak
    print(f"abusive load for {seconds:.0f} s on {url}")
    print("| phase | VmRSS (MiB) |")
    print("|---|---:|")
    print(f"| started, nothing loaded | {start:.0f} |")
    print(f"| baseline: after ordinary use at full concurrency (8 rollouts, a GIF, an MP4) | {baseline:.0f} |")
    print(f"| peak during the abuse | {during:.0f} |")
    waited = 0
    for wait in (15, 45):  # the abandon time is 30 s from a rollout's last read
        time.sleep(wait - waited)
        waited = wait
        print(f"| {wait} s after the abusers ended or left | {rss_mib(pid):.0f} |")
    sampler.done.set()
    keeper.close()
    print("what each kind of request got:")
    for key in sorted(got):
        print(f"  {key}: {got[key]}")


if __name__ == "__main__":
    main()
