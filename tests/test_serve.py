"""The policy server (bpp serve): openpi's wire format, prompts by id and by upload, validation, tokens, isolation
between clients, batching, and the robot-side client reproducing the in-process evaluator."""

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.benchmarks.prompting import run_prompted
from bpp.data.contexts import task_context
from bpp.policies.agent import PolicyAgent
from bpp.policies.registry import get_method
from helpers import ROBOT_PYTHON, config, import_optional

pytestmark = pytest.mark.serve
import_optional("websockets", "serve")
import_optional("msgpack", "serve")

from websockets.exceptions import ConnectionClosed, InvalidStatus  # noqa: E402

from bpp.serve.client import PolicyClient, ServerError  # noqa: E402
from bpp.serve.prompts import PromptLibrary  # noqa: E402
from bpp.serve.robot import RemoteAgent  # noqa: E402
from bpp.serve.server import PolicyServer, ServerLimits, ServerThread  # noqa: E402
from bpp.serve.wire import WireError, pack, unpack  # noqa: E402


def _model(method, store, seed=0):
    torch.manual_seed(seed)
    return get_method(method).model_cls(config(method), store.stats).eval()


def _server(model, store, **kw):
    library = PromptLibrary(model.data_spec(), model.validate_context, store, BENCHMARK.frames)
    return PolicyServer(model, library, {"method": model.method}, **kw)


def _trained_run(store, tmp_path, steps: int):
    """A BPP run of `steps` training steps on `store` (its checkpoint is what `bpp serve` loads)."""
    from bpp.train import TrainConfig, train

    run = tmp_path / "run"
    cfg = TrainConfig(data=store.path, out=run, method="bpp", steps=steps, batch_size=4, workers=0, warmup_steps=1)
    train(cfg, config("bpp"), progress=False)
    return run


def _obs(store, episode, step, keys):
    sl = store.episode_slice(episode)
    return {k: store.array(k)[sl.start + step] for k in keys}


# ----------------------------------------------------------------------------------------------- the wire
def test_the_wire_format_is_openpis_and_round_trips_every_array():
    import msgpack

    message = {
        "state": np.arange(6, dtype=np.float32).reshape(2, 3),
        "image": np.random.default_rng(0).integers(0, 255, (4, 4, 3), dtype=np.uint8),
        "seed": np.int64(7),
        "nested": {"x": [np.float64(1.5), "text"], "flag": True},
    }
    frame = pack(message)
    raw = msgpack.unpackb(frame, strict_map_key=False)  # what openpi's unpacker sees before its object hook
    assert raw["state"] == {
        b"__ndarray__": True,
        b"data": message["state"].tobytes(),
        b"dtype": "<f4",
        b"shape": [2, 3],
    }
    assert raw["seed"] == {b"__npgeneric__": True, b"data": 7, b"dtype": "<i8"}
    back = unpack(frame)
    for key in ("state", "image"):
        assert back[key].dtype == message[key].dtype
        np.testing.assert_array_equal(back[key], message[key])
    assert back["seed"] == 7 and back["seed"].dtype == np.int64 and back["nested"]["x"][1] == "text"
    with pytest.raises(WireError, match="dtype object"):
        pack({"bad": np.array([{}], dtype=object)})
    for garbage in (b"\xc1\xc1", pack({"a": 1})[:-1]):
        with pytest.raises(WireError, match="not a msgpack message"):
            unpack(garbage)
    lying = msgpack.packb({b"__ndarray__": True, b"data": b"\0" * 8, b"dtype": "<f4", b"shape": [3]})
    with pytest.raises(WireError, match="malformed array"):
        unpack(lying)


# ----------------------------------------------------------------------------------------------- exactness
def test_the_robot_client_reproduces_bpp_eval_exactly_rollout_for_rollout(debug_store, tmp_path):
    """A served checkpoint, driven through the socket one rollout per task (as `bpp eval` then runs each task as a
    batch of one), gives every rollout `bpp eval` gives, to the last bit."""
    from bpp.benchmarks.contract import TaskSet
    from bpp.evaluation.evaluate import Protocol, evaluate
    from bpp.serve.command import build_server
    from bpp.serve.robot import RobotClient, robot_client

    run = _trained_run(debug_store, tmp_path, steps=2)
    protocol = Protocol(rollouts=1, seed=3, max_steps=40)
    tasks = [0, 4, 7, 11]  # what --num-tasks 4 spreads over the store's 12
    local = evaluate(run, TaskSet(debug_store, "debug"), tasks, tmp_path / "eval", protocol, 1, 0, progress=False)
    with ServerThread(build_server(run, str(debug_store.path))) as url:
        args = RobotClient(
            tasks=debug_store.path, server=url, num_tasks=4, rollouts=1, seed=3, max_steps=40, client="bpp"
        )
        served = robot_client(args)
    assert served["rollouts"] == local["rollouts"] and served["summary"] == local["summary"]
    assert all(row["steps"] > 8 for row in local["rollouts"])  # several replanning requests each


def test_concurrent_clients_are_batched_and_act_as_in_process(debug_store):
    model = _model("bpp", debug_store)
    episodes, seeds = [0, 7, 20, 30], [5, 6, 7, 8]
    plan = [
        {"target_episode": e, "prompt_episode": e, "board_angle": 0.3 * i, "seed": s}
        for i, (e, s) in enumerate(zip(episodes, seeds, strict=True))
    ]
    local, _ = run_prompted(PolicyAgent(model), BENCHMARK, debug_store, plan, 24, [False] * 4)
    server = _server(model, debug_store, limits=ServerLimits(batch_wait_s=0.05))
    with ServerThread(server) as url:
        remote = RemoteAgent(url, use_openpi=False)
        try:
            remote.start([f"episode:{e}" for e in episodes], seeds)
            served = BENCHMARK.run_rollouts(remote, debug_store, plan, 24, [False] * 4)
        finally:
            remote.close()
    assert max(server.worker.batches) > 1  # requests that arrived together shared one inference call
    for a, b in zip(local, served, strict=True):  # float sums differ with the batch's composition, nothing else
        assert a.steps == b.steps and abs(a.score - b.score) < 1e-2


# ----------------------------------------------------------------------------------------------- every method
@pytest.mark.parametrize("method", ["bpp", "goal_image", "language", "icrt"])
def test_one_client_drives_every_method_by_prompt_id(debug_store, described_store, method):
    store = described_store if method == "language" else debug_store
    model = _model(method, store)
    server = _server(model, store)
    keys = list(model.obs_keys())
    with ServerThread(server) as url:
        client = PolicyClient(url)
        meta = client.get_server_metadata()
        assert meta["method"] == method and list(meta["observation"]) == keys
        assert meta["n_obs_steps"] == model.cfg.horizons.n_obs_steps and meta["context"] == model.context_kind
        task = store.tasks[1]["id"]
        reply = client.infer({**_obs(store, 3, 0, keys), "prompt": f"{task}#1", "seed": 4})
        assert reply["prompt"] == f"episode:{store.task_episodes()[1][1]}"
        assert reply["actions"].shape == tuple(meta["action"]["shape"]) and np.isfinite(reply["actions"]).all()
        client.close()
    # the same prompt and seed in process, as `bpp eval` runs it: the same first Ta actions
    agent = PolicyAgent(model, record_attention=True)
    agent.reset(task_context(store, int(store.task_episodes()[1][1]), agent.data_spec, BENCHMARK.frames), seed=4)
    first = agent.act(_obs(store, 3, 0, keys))
    expected = np.stack([first, *(q[0] for q in agent.queue)])
    np.testing.assert_array_equal(reply["actions"][: len(expected)], expected)


# ----------------------------------------------------------------------------------------------- prompts
def test_changing_the_prompt_or_resetting_starts_a_fresh_episode(debug_store):
    model = _model("bpp", debug_store)
    keys = list(model.obs_keys())
    with ServerThread(_server(model, debug_store)) as url:
        a, b = PolicyClient(url), PolicyClient(url)
        first = a.infer({**_obs(debug_store, 2, 0, keys), "prompt": 2, "seed": 1})["actions"]
        a.infer(_obs(debug_store, 2, 1, keys))  # the episode goes on, with history
        switched = a.infer({**_obs(debug_store, 9, 0, keys), "prompt": "episode:9", "seed": 1})["actions"]
        fresh = b.infer({**_obs(debug_store, 9, 0, keys), "prompt": 9, "seed": 1})["actions"]
        np.testing.assert_array_equal(switched, fresh)  # nothing of episode 2 (prompt, history, noise) remains
        again = a.infer({**_obs(debug_store, 2, 0, keys), "prompt": 2, "seed": 1, "reset": True})["actions"]
        np.testing.assert_array_equal(again, first)
        a.close(), b.close()


def test_an_uploaded_demonstration_prompts_like_the_same_stored_one(debug_store):
    model = _model("bpp", debug_store)
    keys = list(model.obs_keys())
    sl = debug_store.episode_slice(4)
    demo = {"obs": {k: debug_store.array(k)[sl] for k in keys}, "action": debug_store.array("action")[sl]}
    with ServerThread(_server(model, debug_store)) as url:
        client = PolicyClient(url)
        handle = client.infer({"upload": demo})["prompt"]
        assert handle.startswith("upload:")
        by_upload = client.infer({**_obs(debug_store, 0, 0, keys), "prompt": handle, "seed": 2})["actions"]
        by_id = client.infer({**_obs(debug_store, 0, 0, keys), "prompt": 4, "seed": 2})["actions"]
        np.testing.assert_array_equal(by_upload, by_id)
        short = {"obs": {k: v[:3] for k, v in demo["obs"].items()}, "action": demo["action"][:3]}
        with pytest.raises(ServerError, match="at least one chunk"):
            client.infer({"upload": short})
        with pytest.raises(ServerError, match="no such upload"):
            client.infer({**_obs(debug_store, 0, 0, keys), "prompt": "upload:0000", "reset": True})
        client.close()


# ----------------------------------------------------------------------------------------------- refusals
def test_bad_requests_are_answered_with_the_reason_and_change_nothing(debug_store):
    model = _model("bpp", debug_store)
    keys = list(model.obs_keys())
    good = _obs(debug_store, 1, 0, keys)
    nan = dict(good, agent_pos=np.array([np.nan, 0.0], dtype=np.float32))
    cases = [
        ({"prompt": 1, **{k: v for k, v in good.items() if k != "agent_pos"}}, "lacks \\['agent_pos'\\]"),
        ({**good, "prompt": 1, "gripper": np.zeros(1)}, "unknown request fields \\['gripper'\\]"),
        ({**good, "prompt": 1, "agent_pos": np.zeros(3, np.float32)}, "'agent_pos' must have shape \\(2,\\)"),
        ({**nan, "prompt": 1}, "NaN"),
        ({**good, "prompt": "no_such_task"}, "no such task"),
        ({**good, "prompt": 10**6}, "episodes 0..35"),
        ({**good, "prompt": 1, "seed": -1}, "non-negative integer"),
        ({**good, "prompt": 1, "agent_pos": np.zeros((2, 2), np.float32)}, "different numbers of steps"),
        (good, "first request must name a 'prompt'"),
        ([1, 2], "must be a map"),
    ]
    with ServerThread(_server(model, debug_store)) as url:
        client, alone = PolicyClient(url), PolicyClient(url)
        for request, reason in cases:
            with pytest.raises(ServerError, match=reason):
                client.infer(request)
        # the connection is still open and the refused requests left the session as it was
        after = client.infer({**good, "prompt": 1, "seed": 3})["actions"]
        with pytest.raises(ServerError, match="NaN"):
            client.infer(nan)
        second = client.infer(_obs(debug_store, 1, 1, keys))["actions"]
        alone.infer({**good, "prompt": 1, "seed": 3})
        np.testing.assert_array_equal(second, alone.infer(_obs(debug_store, 1, 1, keys))["actions"])
        assert after.shape == second.shape
        # frames outside the protocol close the connection deliberately
        client._ws.send("hello")
        assert "binary msgpack" in client._ws.recv(5)
        with pytest.raises(ConnectionClosed):
            client._ws.recv(5)
        alone._ws.send(b"\xc1")
        assert "not a msgpack message" in alone._ws.recv(5)
        with pytest.raises(ConnectionClosed):
            alone._ws.recv(5)


def test_oversized_messages_close_only_their_connection(debug_store):
    model = _model("bpp", debug_store)
    keys = list(model.obs_keys())
    with ServerThread(_server(model, debug_store, limits=ServerLimits(max_message_bytes=4096))) as url:
        big, other = PolicyClient(url), PolicyClient(url)
        with pytest.raises(ConnectionClosed) as closed:
            big.infer({"upload": {"obs": {"x": np.zeros(10_000, np.float32)}, "action": np.zeros(1)}})
        assert closed.value.rcvd.code == 1009  # message too big
        assert other.infer({**_obs(debug_store, 0, 0, keys), "prompt": 0})["actions"].ndim == 2


def test_a_token_is_required_and_loopback_is_the_default(debug_store):
    from bpp.cli import main

    model = _model("bpp", debug_store)
    with ServerThread(_server(model, debug_store, token="s3cret")) as url:
        for key in (None, "wrong", "s3cre", "s3cret2"):
            with pytest.raises(InvalidStatus) as refused:
                PolicyClient(url, api_key=key)
            assert refused.value.response.status_code == 401
        PolicyClient(url, api_key="s3cret").close()
    with pytest.raises(SystemExit, match="exposes the policy beyond this machine: set a token"):
        main(["serve", "runs/none", "--host", "0.0.0.0"])


def test_a_client_that_leaves_mid_request_costs_others_nothing(debug_store):
    model = _model("bpp", debug_store)
    keys = list(model.obs_keys())
    steps = [_obs(debug_store, 6, t, keys) for t in range(3)]
    with ServerThread(_server(model, debug_store, limits=ServerLimits(batch_wait_s=0.05))) as url:
        reference = PolicyClient(url)
        expected = [reference.infer({**steps[0], "prompt": 6, "seed": 1})["actions"]]
        expected += [reference.infer(s)["actions"] for s in steps[1:]]
        stays, leaves = PolicyClient(url), PolicyClient(url)
        got = []
        for t, s in enumerate(steps):
            if t < 2:
                leaves._ws.send(pack({**s, "prompt": 2}))  # never reads its replies
            if t == 1:
                leaves._ws.close()
            got.append(stays.infer({**s, "prompt": 6, "seed": 1} if t == 0 else s)["actions"])
        for a, b in zip(expected, got, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-4)  # maybe batched with the leaver: float sums only


# ----------------------------------------------------------------------------------------------- robot side
def test_the_robot_side_runs_without_torch(debug_store, tmp_path):
    """The robot computer needs no torch: the robot client runs in a process where importing torch fails."""
    model = _model("bpp", debug_store)
    out = tmp_path / "robot.json"
    code = (
        "import sys\n"
        "class NoTorch:  # as if torch were not installed\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] == 'torch':\n"
        "            raise ModuleNotFoundError(f'No module named {name!r}', name=name)\n"
        "sys.meta_path.insert(0, NoTorch())\n"
        "from bpp.serve.robot import main\n"
        f"main(['--server', sys.argv[1], '--tasks', {str(debug_store.path)!r}, '--num-tasks', '2', '--rollouts', '2',"
        f" '--max-steps', '16', '--client', 'bpp', '--out', {str(out)!r}])\n"
    )
    with ServerThread(_server(model, debug_store)) as url:
        done = subprocess.run([sys.executable, "-c", code, url], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "distance" in done.stdout or "chamfer" in done.stdout.lower()
    import json

    data = json.loads(out.read_text())
    assert data["summary"]["rollouts"] == 4 and data["protocol"]["rollouts"] == 2


@pytest.mark.openpi
def test_openpis_own_client_drives_a_served_checkpoint_to_bpp_evals_scores(debug_store, tmp_path):
    """A robot environment with openpi's client (numpy < 2) and no torch (`make install-all` builds it) runs the
    protocol against `bpp serve`'s server for a trained checkpoint; with one rollout per task, so that `bpp eval`
    batches nothing either, every rollout matches `bpp eval`'s."""
    import json

    from bpp.benchmarks.contract import TaskSet
    from bpp.evaluation.evaluate import Protocol, evaluate
    from bpp.serve.command import build_server

    run = _trained_run(debug_store, tmp_path, steps=2)
    protocol = Protocol(rollouts=1, seed=0, max_steps=30)
    tasks = [0, 4, 7, 11]  # what --num-tasks 4 spreads over the store's 12
    local = evaluate(run, TaskSet(debug_store, "debug"), tasks, tmp_path / "eval", protocol, 1, 0, progress=False)
    out = tmp_path / "robot.json"
    with ServerThread(build_server(run, str(debug_store.path), token="t0ken")) as url:
        env = {**os.environ, "BPP_SERVE_TOKEN": "t0ken"}
        args = ["--server", url, "--tasks", str(debug_store.path), "--num-tasks", "4", "--rollouts", "1", "--seed", "0"]
        args += ["--max-steps", "30", "--client", "openpi", "--out", str(out)]
        done = subprocess.run(
            [str(ROBOT_PYTHON), "-m", "bpp.serve.robot", *args], capture_output=True, text=True, env=env, timeout=600
        )
    assert done.returncode == 0, done.stderr
    served = json.loads(out.read_text())
    assert served["client"].startswith("openpi_client") and served["served"]["train_step"] == 2
    # The robot environment simulates with numpy 1.26 (openpi's client needs numpy < 2), `bpp eval` here with numpy 2,
    # whose float functions differ in the last bits: the same rollouts, scores equal to 1e-9.
    assert len(served["rollouts"]) == len(local["rollouts"]) == len(tasks)
    for got, want in zip(served["rollouts"], local["rollouts"], strict=True):
        assert got.keys() == want.keys()
        for key in got:
            assert got[key] == (pytest.approx(want[key], rel=1e-9) if isinstance(want[key], float) else want[key])
    assert served["summary"]["score_mean"] == pytest.approx(local["summary"]["score_mean"], rel=1e-9)


def test_bpp_serve_starts_serves_and_stops_on_ctrl_c(debug_store, tmp_path):
    import re
    import signal

    run = _trained_run(debug_store, tmp_path, steps=1)
    proc = subprocess.Popen(
        [sys.executable, "-m", "bpp.cli", "serve", str(run), "--prompts", str(debug_store.path), "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = proc.stdout.readline()
        found = re.search(r"on (ws://127\.0\.0\.1:\d+) \(no token: loopback only\); prompts: 36 demonstrations", line)
        assert found, line + proc.stderr.read() if proc.poll() is not None else line
        client = PolicyClient(found.group(1))
        assert client.get_server_metadata()["train_step"] == 1
        keys = list(client.get_server_metadata()["observation"])
        assert client.infer({**_obs(debug_store, 0, 0, keys), "prompt": 0})["actions"].ndim == 2
        client.close()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 0 and "stopped after 1 requests" in out and "Traceback" not in err
