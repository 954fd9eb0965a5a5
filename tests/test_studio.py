"""The studio (bpp studio): its API's guarantees, its Python client, and its page driven by a real browser."""

import base64
import io
import json
import os
import shutil
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from helpers import config, import_optional

httpx = import_optional("httpx", "studio")
import_optional("fastapi", "studio")

from bpp.benchmarks.draw.studio.client import StudioClient, StudioClientError  # noqa: E402
from bpp.benchmarks.draw.studio.command import server_config  # noqa: E402
from bpp.benchmarks.draw.studio.engine import Studio  # noqa: E402
from bpp.benchmarks.draw.studio.state import Limits, find_checkpoints  # noqa: E402
from bpp.train import TrainConfig, train  # noqa: E402

pytestmark = pytest.mark.studio

TOKEN = "test-token-0123456789abcdef"
TRIANGLE = [[[0.2, 0.2], [0.8, 0.2], [0.5, 0.8], [0.2, 0.2]]]


@pytest.fixture(scope="module")
def runs(tmp_path_factory, debug_store):
    root = tmp_path_factory.mktemp("runs")
    for method in ("bpp", "icrt"):
        cfg = TrainConfig(
            data=debug_store.path, out=root / method, method=method, steps=1, batch_size=4, workers=0, warmup_steps=1
        )
        train(cfg, config(method), progress=False)
    return root


class Server:
    """A studio served by uvicorn on a free loopback port, in a thread."""

    def __init__(self, runs: Path, workdir: Path, limits: Limits, data_dir: Path):
        import uvicorn

        from bpp.benchmarks.draw.studio.server import create_app

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self.studio = Studio(find_checkpoints([runs]), workdir, limits, data_dir=data_dir)
        config_ = server_config(create_app(self.studio, TOKEN), limits, host="127.0.0.1", port=self.port)
        self.server = uvicorn.Server(config_)
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        deadline = time.time() + 30
        while not self.server.started and time.time() < deadline:
            time.sleep(0.05)

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10)
        self.studio.close()


@pytest.fixture(scope="module")
def server(runs, tmp_path_factory):
    data_dir = tmp_path_factory.mktemp("data")
    srv = Server(runs, tmp_path_factory.mktemp("work"), Limits(abandon_s=2.0, max_body_bytes=200_000), data_dir)
    yield srv
    srv.stop()


def client(server) -> StudioClient:
    return StudioClient(server.url, TOKEN)


def test_every_api_call_needs_the_token(server):
    from bpp.benchmarks.draw.studio.server import create_app

    routes = [(m, r.path) for r in create_app(server.studio, TOKEN).routes for m in getattr(r, "methods", ())]
    paths = [(m, p.replace("{pid}", "x").replace("{rid}", "x").replace("{fmt}", "gif")) for m, p in routes]
    api = [(m, p) for m, p in paths if p.startswith("/api")]
    assert len(api) >= 12
    with client(server) as c:  # a valid session: only the token is missing or wrong
        for method, path in api:
            for headers, params in (({}, {}), ({"Authorization": "Bearer wrong-token-0000000"}, {"token": "x"})):
                response = httpx.request(
                    method,
                    f"{server.url}{path}",
                    headers={**headers, "X-Studio-Session": c.session},
                    params=params,
                    json={} if method == "POST" else None,
                )
                assert response.status_code == 401 and response.json()["field"] == "token", (method, path)
    # a token in a URL leaks (history, logs, Referer): the API takes it only in a header (or as the page's cookie)
    assert httpx.post(f"{server.url}/api/session", params={"token": TOKEN}).status_code == 401
    assert httpx.post(f"{server.url}/api/session", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200
    page = httpx.get(server.url)  # the page itself holds no data; its calls need the token its address brings
    assert page.status_code == 200 and "bpp studio" in page.text


def test_a_rollout_streams_steps_and_is_downloadable(server, tmp_path):
    with client(server) as c:
        checkpoints = {ck["method"]: ck["id"] for ck in c.checkpoints()}
        assert set(checkpoints) == {"bpp", "icrt"}
        prompt = c.prompt_strokes(TRIANGLE, board_angle=0.3)
        rollout = c.rollout(prompt["id"], checkpoints["bpp"], board_angle=-0.4, max_steps=30)
        events = list(c.events(rollout["id"]))
        steps = [e for e in events if e["type"] == "step"]
        assert events[0]["type"] == "start" and events[-1]["type"] == "end" and events[-1]["status"] == "done"
        assert len(steps) == 30 and all(len(e["action"]) == 3 and np.isfinite(e["chamfer"]) for e in steps)
        assert any("attention" in e for e in steps)  # a new inference brings a new attention column
        framed = c.rollout(prompt["id"], checkpoints["icrt"], board_angle=0.1, max_steps=3, frames=64)
        last = [e for e in c.events(framed["id"]) if e["type"] == "step"][-1]
        assert Image.open(io.BytesIO(base64.b64decode(last["frame"]))).size == (64, 64)
        episode = c.episode(rollout["id"])
        assert episode["best_chamfer"] == events[-1]["best_chamfer"] and len(episode["actions"]) == 30
        gif = c.download(rollout["id"], tmp_path / "r.gif")
        assert gif.read_bytes()[:3] == b"GIF"
        task = tmp_path / "task.json"
        task.write_text(json.dumps(c.task_file(prompt["id"])))
        from bpp.drawing.files import load_drawings

        assert len(load_drawings(task)[0].strokes) == 1  # a task file `bpp eval --files` accepts


def test_every_kind_of_prompt(server, tmp_path):
    svg = tmp_path / "v.svg"
    svg.write_text('<svg xmlns="http://www.w3.org/2000/svg"><polyline points="10,10 50,90 90,10"/></svg>')
    samples = [[100 + 6 * i, 200 + 3 * i, 1 if 2 <= i < 30 else 0] for i in range(35)]
    with client(server) as c:
        drawn = c.prompt_drawn(samples, board_angle=0.2)
        assert drawn["source"] == "drawn" and drawn["steps"] == 35 + 5  # the demonstrator's 5 resting steps
        assert c.prompt_file(svg)["source"] == "file v.svg"
        stored = c.prompt_stored(task=3, demo=1)
        assert stored["source"] == "stored" and stored["steps"] > 10


@pytest.mark.parametrize(
    ("body", "status", "field"),
    [
        ({"kind": "drawn", "samples": [[1, 2]]}, 422, "samples"),
        ({"kind": "drawn", "samples": [[1, 2, 0], [3, 4, 0]]}, 422, "samples"),  # never pen down
        ({"kind": "drawn", "samples": [[1, 2, 1], [3e9, 4, 1]]}, 422, "samples"),
        ({"kind": "drawn", "samples": [[1, 2, 1]] * 2, "board_angle": 9}, 422, "board_angle"),
        ({"kind": "strokes", "strokes": [[[0.2, 1.5], [0.3, 0.3]]]}, 422, "strokes"),
        ({"kind": "stored", "task": 999}, 422, "task"),
        ({"kind": "file", "name": "x.txt", "text": "hello"}, 422, "name"),
        ({"kind": "file", "name": "x.json", "text": "[" * 5000}, 422, "text"),
        ({"kind": "nope"}, 422, "kind"),
        ({"kind": "stored", "task": 1, "path": "/etc/passwd"}, 422, "path"),
    ],
)
def test_bad_fields_get_a_4xx_naming_them(server, body, status, field):
    with client(server) as c, pytest.raises(StudioClientError) as err:
        c._call("POST", "/api/prompts", body)
    assert err.value.status == status and err.value.field == field, err.value


def test_limits_on_body_size_prompt_length_and_rollouts(server):
    with client(server) as c:
        with pytest.raises(StudioClientError) as err:
            c._call("POST", "/api/prompts", {"kind": "file", "name": "x.json", "text": " " * 300_000})
        assert err.value.status == 413 and err.value.field == "body"
        headers = {
            "Authorization": f"Bearer {TOKEN}",
            "X-Studio-Session": c.session,
            "Content-Type": "application/json",
        }
        chunks = (b" " * 50_000 for _ in range(10))  # no Content-Length: cut off once past the limit
        chunked = httpx.post(f"{server.url}/api/prompts", content=chunks, headers=headers)
        assert chunked.status_code == 413 and chunked.json()["field"] == "body"
        bad_json = httpx.post(f"{server.url}/api/prompts", content=b'{"kind": ', headers=headers)
        assert bad_json.status_code == 422 and bad_json.json()["field"] == "body"
        with pytest.raises(StudioClientError) as err:
            c.prompt_drawn([[100.0, 100.0, 1.0]] * 900)
        assert err.value.status == 413 and "at most 795" in err.value.detail
        prompt = c.prompt_strokes(TRIANGLE)
        bpp = next(ck["id"] for ck in c.checkpoints() if ck["method"] == "bpp")
        with pytest.raises(StudioClientError) as err:
            c.rollout(prompt["id"], bpp, max_steps=5000)
        assert err.value.status == 422 and err.value.field == "max_steps"
        started = [
            c.rollout(prompt["id"], bpp, max_steps=1000) for _ in range(server.studio.limits.max_rollouts_per_session)
        ]
        with pytest.raises(StudioClientError) as err:
            c.rollout(prompt["id"], bpp)
        assert err.value.status == 429 and "this session already runs" in err.value.detail
        for rollout in started:
            assert c.stop(rollout["id"])["id"] == rollout["id"]


def test_sessions_do_not_see_each_other(server):
    with client(server) as a, client(server) as b:
        prompt = a.prompt_strokes(TRIANGLE)
        bpp = next(ck["id"] for ck in a.checkpoints() if ck["method"] == "bpp")
        rollout = a.rollout(prompt["id"], bpp, max_steps=20)
        for call in (
            lambda: b.task_file(prompt["id"]),
            lambda: b.status(rollout["id"]),
            lambda: b.stop(rollout["id"]),
            lambda: b.rollout(prompt["id"], bpp),
            lambda: list(b.events(rollout["id"])),
            lambda: b.episode(rollout["id"]),
            lambda: b.download(rollout["id"], Path("/nonexistent/x.gif")),
        ):
            with pytest.raises(StudioClientError) as err:
                call()
            assert err.value.status == 404
        assert a.run(prompt["id"], bpp, max_steps=10)["status"] == "done"  # a's own work is undisturbed


def test_abandoned_and_disconnected_rollouts_are_stopped(server):
    with client(server) as c:
        prompt = c.prompt_strokes(TRIANGLE)
        bpp = next(ck["id"] for ck in c.checkpoints() if ck["method"] == "bpp")
        nobody = c.rollout(prompt["id"], bpp, max_steps=1000)  # started, never read
        left = c.rollout(prompt["id"], bpp, max_steps=1000)
        for event in c.events(left["id"]):  # read a few steps, then hang up
            if event["type"] == "step" and event["step"] >= 3:
                break
        deadline = time.time() + 30
        while time.time() < deadline and server.studio.sessions[c.session].rollouts[nobody["id"]].running:
            time.sleep(0.2)
        assert server.studio.sessions[c.session].rollouts[nobody["id"]].status == "abandoned"
        assert c.status(left["id"])["status"] == "stopped" and c.status(left["id"])["steps"] < 1000


_WRITES: list[str] = []
_RECORDING = threading.Event()


def _record_writes(event: str, args) -> None:
    """An audit hook (it stays for the whole test process, so it records only while a test asks)."""
    if _RECORDING.is_set() and event == "open" and isinstance(args[0], (str, bytes, Path)):
        mode, flags = args[1] or "", args[2] or 0
        if any(c in str(mode) for c in "wax+") or flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            _WRITES.append(os.fsdecode(args[0]))


def test_no_client_path_touches_the_file_system(server):
    sys.addaudithook(_record_writes)
    names = ("../../../../tmp/studio-pwn.json", "/tmp/studio-pwn.svg", "..\\..\\studio-pwn.json")
    svg = '<svg xmlns="http://www.w3.org/2000/svg"><line x1="0" y1="0" x2="9" y2="9"/></svg>'
    _RECORDING.set()
    try:
        with client(server) as c:
            for name in names:
                text = json.dumps({"drawings": [{"id": "x", "strokes": TRIANGLE}]}) if name.endswith(".json") else svg
                assert c._call("POST", "/api/prompts", {"kind": "file", "name": name, "text": text})["steps"] > 0
    finally:
        _RECORDING.clear()
    workdir = str(Path(server.studio.workdir).resolve())
    assert _WRITES, "the audit hook saw no writes at all: it cannot vouch for anything"
    outside = [w for w in _WRITES if not str(Path(w).resolve()).startswith(workdir)]
    assert not outside, f"writes outside the studio's folder: {outside[:5]}"
    assert not any("studio-pwn" in w for w in _WRITES)


def test_the_command_binds_loopback_by_default():
    from bpp.benchmarks.draw.studio.command import StudioCommand

    assert StudioCommand().host == "127.0.0.1"
    with pytest.raises(ValueError, match="token must be at least 16"):
        StudioCommand(token="short")


@pytest.mark.browser
def test_a_person_draws_a_prompt_and_watches_the_policy(server, tmp_path):
    """Debian's chromium, driven by Playwright as a person would: draw, use the drawing, run, watch."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    assert chromium, "the browser test needs Debian's chromium: `make install` installs it (apt-get install chromium)"
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
        page = browser.new_page(viewport={"width": 1300, "height": 900})
        page.goto(f"{server.url}/?token={TOKEN}")
        page.wait_for_selector("#side-a .checkpoint option", state="attached")
        box = page.locator("#prompt-top").bounding_box()
        x0, y0 = box["x"] + box["width"] * 0.3, box["y"] + box["height"] * 0.35
        page.mouse.move(x0, y0)
        page.mouse.down()
        for i in range(1, 16):  # a stroke over 1.5 s, so the 10 Hz sampler records it
            page.mouse.move(x0 + i * box["width"] * 0.025, y0 + i * box["height"] * 0.015)
            page.wait_for_timeout(100)
        page.mouse.up()
        page.wait_for_timeout(300)
        page.click("#use-drawing")
        page.wait_for_selector("#run:not([disabled])")
        page.wait_for_selector("#prompt-info:text-matches('^prompt ready')")  # selectors: the page's CSP forbids eval
        page.click("#run")
        page.wait_for_selector("#score-a[data-done='1']", state="attached", timeout=120_000)
        score = page.inner_text("#score-a")
        inked = page.evaluate(
            "() => { const d = document.getElementById('ink-a').getContext('2d').getImageData(0, 0, 512, 512).data;"
            " let n = 0; for (let i = 3; i < d.length; i += 4) n += d[i] > 0; return n; }"
        )
        page.screenshot(path=str(tmp_path / "studio.png"), full_page=True)
        artifacts = Path("outputs/test-artifacts")  # kept for a person to look at (outputs/ is not tracked)
        artifacts.mkdir(parents=True, exist_ok=True)
        shutil.copy(tmp_path / "studio.png", artifacts / "studio.png")
        browser.close()
    assert "best Chamfer" in score and "px" in score, score
    assert inked > 50, f"the policy's ink did not appear on the page ({inked} pixels)"


def test_a_session_keeps_only_its_newest_finished_rollouts(server):
    from bpp.benchmarks.draw.studio.engine import KEEP_FINISHED_ROLLOUTS

    with client(server) as c:
        prompt = c.prompt_strokes(TRIANGLE)
        bpp = next(ck["id"] for ck in c.checkpoints() if ck["method"] == "bpp")
        ids = [c.run(prompt["id"], bpp, max_steps=1)["id"] for _ in range(KEEP_FINISHED_ROLLOUTS + 3)]
        kept = server.studio.sessions[c.session].rollouts
        assert len(kept) <= KEEP_FINISHED_ROLLOUTS + 1 and ids[-1] in kept and ids[0] not in kept
        with pytest.raises(StudioClientError) as err:
            c.status(ids[0])
        assert err.value.status == 404
