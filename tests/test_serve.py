"""The policy server (bpp serve): openpi's wire format, prompts by id and by upload, validation, tokens, isolation
between clients, batching, and the robot-side client reproducing the in-process evaluator."""

import json
import logging
import os
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np
import pytest
import torch

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.core.prompting import run_prompted
from bpp.data.contexts import task_context
from bpp.policies.agent import PolicyAgent
from bpp.policies.registry import get_method
from helpers import ROBOT_PYTHON, config, import_optional

pytestmark = pytest.mark.serve
import_optional("websockets", "serve")
import_optional("msgpack", "serve")

from websockets.exceptions import ConnectionClosed, InvalidStatus  # noqa: E402

from bpp.network import urls  # noqa: E402
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


def _demo(store, episode, keys):
    """Episode `episode` of `store` as an upload: its observations of `keys` and its actions."""
    sl = store.episode_slice(episode)
    return {"obs": {k: store.array(k)[sl] for k in keys}, "action": store.array("action")[sl]}


def _wait_for(condition, what: str, timeout: float = 10.0) -> None:
    """Wait until `condition()` holds (something the server does after a client leaves)."""
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


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
    from bpp.core.contract import TaskSet
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


@pytest.mark.parametrize("memory", [0, 2], ids=["bpp", "with-rollout-memory"])
def test_concurrent_clients_are_batched_and_act_as_in_process(debug_store, memory):
    torch.manual_seed(0)
    cfg = config("bpp")
    cfg = replace(cfg, prompt=replace(cfg.prompt, rollout_memory=memory))
    model = get_method("bpp").model_cls(cfg, debug_store.stats).eval()
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
    assert max(server.worker.batch_sizes) > 1  # requests that arrived together shared one inference call
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


def test_the_prompt_field_takes_openpis_instruction_text_where_the_method_reads_text(debug_store, described_store):
    """openpi's servers read an observation's 'prompt' as the instruction: a Language policy takes it so (a known id
    still names its prompt), and any other policy's refusal says what bpp reads there instead."""
    text = "draw a wide spiral"  # no task's id
    model = _model("language", described_store)
    keys = list(model.obs_keys())
    with ServerThread(_server(model, described_store)) as url:
        client = PolicyClient(url)
        first = client.infer({**_obs(described_store, 0, 0, keys), "prompt": text, "seed": 1})
        # openpi's robot scripts send the same prompt with every observation: the episode goes on
        second = client.infer({**_obs(described_store, 0, 1, keys), "prompt": text})
        assert first["prompt"] == second["prompt"] == text and second["episode_step"] == 1
        task = described_store.tasks[2]["id"]
        assert client.infer({**_obs(described_store, 0, 0, keys), "prompt": task})["prompt"].startswith("episode:")
        client.close()
    agent = PolicyAgent(model)
    agent.reset({"text": text}, seed=1)
    expected = [agent.act(_obs(described_store, 0, 0, keys)), *(q[0] for q in agent.queue)]
    np.testing.assert_array_equal(first["actions"][: len(expected)], np.stack(expected))

    bpp = _model("bpp", debug_store)
    keys = list(bpp.obs_keys())
    with ServerThread(_server(bpp, debug_store)) as url, pytest.raises(ServerError) as refused:
        PolicyClient(url).infer({**_obs(debug_store, 0, 0, keys), "prompt": text})
    for says in ("no such task", "bpp reads 'prompt' as the id of a demonstration", "openpi's servers read it as"):
        assert says in str(refused.value)


def test_uploads_are_held_by_connections_and_bounded(debug_store):
    """An upload lives while its connection is open, while an episode runs it, or while it is the newest; each
    connection holds a few, all of them together a bounded size."""
    model = _model("bpp", debug_store)
    keys = list(model.obs_keys())
    demos = [_demo(debug_store, e, keys) for e in range(5)]
    size = [sum(v.nbytes for v in d["obs"].values()) + d["action"].nbytes for d in demos]  # all float32 already
    limit = size[1] + size[2] + size[3] + 16
    library = PromptLibrary(
        model.data_spec(), model.validate_context, debug_store, BENCHMARK.frames, 2, max_upload_bytes=limit
    )
    good = {**_obs(debug_store, 0, 0, keys), "seed": 0}
    with ServerThread(PolicyServer(model, library, {"method": "bpp"})) as url:
        a, b, c = PolicyClient(url), PolicyClient(url), PolicyClient(url)
        handles = [a.infer({"upload": demos[e]})["prompt"] for e in range(3)]
        assert library.upload_bytes == size[1] + size[2]  # a holds its newest two
        with pytest.raises(ServerError, match="no such upload"):
            a.infer({**good, "prompt": handles[0]})
        newest = b.infer({"upload": demos[3]})["prompt"]
        with pytest.raises(ServerError, match=r"over its limit of .* MiB; uploads are let go as the connections"):
            b.infer({"upload": demos[4]})
        c.infer({**good, "prompt": handles[1]})  # c's episode runs one of a's uploads
        a.close()
        _wait_for(lambda: library.upload_bytes == size[1] + size[3], "a's uploads to be let go")
        c.close()
        _wait_for(lambda: library.upload_bytes == size[3], "c's episode to let go of a's upload")
        b.close()
        # the newest stays after its connection closed: the hand-off of `bpp iphumi prompt` to a robot
        robot = PolicyClient(url)
        assert robot.infer({**good, "prompt": "upload:latest"})["prompt"] == newest
        assert library.upload_bytes == size[3]
        robot.close()


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


def test_malformed_requests_are_refused_by_name_and_log_no_traceback(debug_store, caplog):
    """Ragged observations, prompt ids the parser cannot read, malformed uploads and a client that vanishes without a
    close frame: each gets a reply naming the field (the vanished one a quiet log line), no traceback is logged, and
    the server goes on serving."""
    caplog.set_level(logging.INFO)
    model = _model("bpp", debug_store)
    keys = list(model.obs_keys())
    good = _obs(debug_store, 1, 0, keys)
    demo = _demo(debug_store, 4, keys)
    task = debug_store.tasks[0]["id"]
    cases = [
        ({**good, "prompt": 1, "agent_pos": [[1.0, 2.0], [3.0]]}, "'agent_pos' must be an array or equally long lists"),
        ({**good, "prompt": "episode:" + "9" * 5000}, "\\(5008 characters\\) has over 2000 characters"),
        ({**good, "prompt": "episode:" + "9" * 100}, "'episode:' takes an episode number, 0..35 in digits 0-9"),
        ({**good, "prompt": "episode:\u00b2"}, "'episode:' takes an episode number"),
        ({**good, "prompt": "episode:\u0663"}, "'episode:' takes an episode number"),
        ({**good, "prompt": f"{task}#\u0663"}, "has demonstrations #0..#2"),
        ({**good, "prompt": 1, 7: 1, b"x": 2}, "unknown request fields"),
        ({"upload": {**demo, "obs": {**demo["obs"], "agent_pos": [[1.0], [2.0, 3.0]]}}}, "upload obs 'agent_pos'"),
        ({"upload": {**demo, "action": "x"}}, "upload 'action' must be an array, got str"),
        ({"upload": {**demo, "action": np.full(demo["action"].shape, "x")}}, "upload 'action' must be floating"),
        ({"upload": {**demo, "obs": [1, 2]}}, "upload lacks 'obs'"),
        ({"upload": {**demo, "actions": demo["action"]}}, "upload fields \\['actions'\\] are unknown"),
    ]
    with ServerThread(_server(model, debug_store)) as url:
        client, other = PolicyClient(url), PolicyClient(url)
        for request, reason in cases:
            with pytest.raises(ServerError, match=reason):
                client.infer(request)
        vanishing = PolicyClient(url)
        vanishing._ws.send(pack({**good, "prompt": 1}))
        vanishing._ws.socket.close()  # gone without a close frame, before its reply
        _wait_for(lambda: "vanished" in caplog.text, "the server to notice the vanished client")
        for c in (client, other):  # both connections serve on
            assert c.infer({**good, "prompt": 1})["actions"].ndim == 2
        client.close(), other.close()
    assert not [r for r in caplog.records if r.exc_info or r.levelno >= logging.ERROR], caplog.text
    assert "Traceback" not in caplog.text


def test_observations_of_the_wrong_kind_or_far_outside_the_training_range_are_refused(debug_store):
    """Booleans, integers, values beyond float32 or beyond any training range (3e38 makes every action NaN) are
    refused at the door, by key and problem, in requests and uploads alike; a value a little outside the training
    range is a reading and is served."""
    model = _model("bpp", debug_store)
    keys = list(model.obs_keys())
    good = {**_obs(debug_store, 1, 0, keys), "prompt": 1}
    demo = _demo(debug_store, 4, keys)
    steps = len(demo["action"])
    far = demo["obs"]["agent_pos"].copy()
    far[3] = 3e38
    cases = [
        ({**good, "agent_pos": np.array([True, False])}, "'agent_pos' must be floating point \\(float32\\), got bool"),
        ({**good, "agent_pos": [True, False]}, "'agent_pos' must be floating point \\(float32\\), got bool"),
        ({**good, "agent_pos": np.array([100, 200])}, "'agent_pos' must be floating point \\(float32\\), got int64"),
        ({**good, "pen_down": np.array(["1"])}, "'pen_down' must be floating point \\(float32\\), got <U1"),
        ({**good, "agent_pos": np.array([3e38, 1.0], np.float32)}, "'agent_pos' holds 3e\\+38 at index \\(0, 0\\)"),
        ({**good, "agent_pos": np.array([1.0, 1e300])}, "'agent_pos' holds 1e\\+300 at index \\(0, 1\\)"),
        ({**good, "agent_pos": np.array([1.0, -np.inf])}, "'agent_pos' contains NaN or infinite values"),
        ({"upload": {**demo, "action": np.ones((steps, 3), bool)}}, "upload 'action' must be floating point"),
        (
            {"upload": {**demo, "obs": {**demo["obs"], "agent_pos": far}}},
            "'agent_pos' holds 3e\\+38 at index \\(3, 0\\)",
        ),
    ]
    with ServerThread(_server(model, debug_store)) as url:
        client = PolicyClient(url)
        for request, reason in cases:
            with pytest.raises(ServerError, match=reason):
                client.infer(request)
        low, high = debug_store.stats["agent_pos"]["min"], debug_store.stats["agent_pos"]["max"]
        outside = np.array([2 * high[0] - low[0], low[1]])  # one range beyond the training data, as float64
        assert np.isfinite(client.infer({**good, "agent_pos": outside})["actions"]).all()
        client.close()


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
    # beyond loopback a token must resist guessing, as the studio's must
    for weak in ("abc", "fifteen-chars-x", "sixteen chars  x", "sixteen-chärs-xx"):
        with pytest.raises(SystemExit, match="must be at least 16 visible ASCII characters"):
            main(["serve", "runs/none", "--host", "0.0.0.0", "--token", weak])
    with pytest.raises(SystemExit, match="runs/none: no such checkpoint"):  # past the token check
        main(["serve", "runs/none", "--host", "0.0.0.0", "--token", "sixteen-chars-xx"])
    assert urls("ws", "0.0.0.0", 8000)[-1] == "ws://127.0.0.1:8000"
    assert not any("0.0.0.0" in url for url in urls("ws", "0.0.0.0", 8000))


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

    from bpp.core.contract import TaskSet
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


def test_bpp_serve_on_every_interface_prints_its_addresses_serves_and_stops_on_ctrl_c(debug_store, tmp_path):
    """`bpp serve --host 0.0.0.0` prints addresses a client can open (not 0.0.0.0), tells its clients the control
    rate and names (no path of the server's), and names its own flags in its errors."""
    import re
    import signal

    from bpp.cli import main

    run = _trained_run(debug_store, tmp_path, steps=1)
    with pytest.raises(SystemExit, match="--prompts 'nope': not a task set of drawanything"):
        main(["serve", str(run), "--prompts", "nope"])
    token = "a-token-of-24-characters"
    proc = subprocess.Popen(
        [sys.executable, "-m", "bpp.cli", "serve", str(run), "--prompts", str(debug_store.path), "--port", "0"]
        + ["--host", "0.0.0.0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "BPP_SERVE_TOKEN": token},
    )
    try:
        line = proc.stdout.readline()
        found = re.search(
            r"on (?:ws://[\d.]+:\d+, )*(ws://127\.0\.0\.1:\d+) \(all interfaces; token required\); prompts: 36", line
        )
        assert found and "0.0.0.0" not in line, line + proc.stderr.read() if proc.poll() is not None else line
        client = PolicyClient(found.group(1), api_key=token)
        meta = client.get_server_metadata()
        assert meta["train_step"] == 1 and meta["control_hz"] == 10  # DrawAnything's robot
        assert meta["checkpoint"] == "run/step_00000001" and meta["prompts"]["store"] == "debug.zarr"
        assert str(tmp_path) not in json.dumps(meta) and str(debug_store.path.parent) not in json.dumps(meta)
        assert client.infer({**_obs(debug_store, 0, 0, list(meta["observation"])), "prompt": 0})["actions"].ndim == 2
        client.close()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 0 and "stopped after 1 requests" in out and "Traceback" not in err
