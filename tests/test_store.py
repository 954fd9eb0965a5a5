import json
import multiprocessing as mp
import pickle
import re
from dataclasses import replace

import numpy as np
import pytest

from bpp.benchmarks.draw.dataset import PRESETS, generate
from bpp.core import registry
from bpp.data import store as store_module
from bpp.data.integrity import StoreError
from bpp.data.merge import merge_stores
from bpp.data.prompt_dataset import finite_statistics
from bpp.data.store import EpisodeStore, EpisodeWriter, with_derived
from bpp.errors import UserError


def _write(path, episodes=3, **kw):
    with EpisodeWriter(path, benchmark="test", config={"a": 1}, chunk_steps=4, **kw) as w:
        t = w.add_task("task-a", {"note": "x"}, points=np.arange(6.0).reshape(3, 2))
        u = w.add_task("task-b", instruction="pick up the bowl", points=np.ones((1, 2)))
        for e in range(episodes):
            n = 3 + e
            w.add_episode(
                {"obs": np.full((n, 2), e, np.float32), "action": np.arange(n, dtype=np.float64)[:, None]},
                t if e % 2 == 0 else u,
                angle=0.1 * e,
                goal=np.full((2, 2), e, np.uint8),
            )
    return EpisodeStore(path)


def test_round_trip(tmp_path):
    s = _write(tmp_path / "s.zarr")
    assert (s.num_tasks, s.num_episodes, s.num_steps) == (2, 3, 12)
    np.testing.assert_array_equal(s.episode_ends, [3, 7, 12])
    np.testing.assert_array_equal(s.episode(1)["obs"], np.full((4, 2), 1, np.float32))
    np.testing.assert_allclose(s.column("angle"), [0.0, 0.1, 0.2])
    np.testing.assert_array_equal(s.column("task_index"), [0, 1, 0])
    assert [list(x) for x in s.task_episodes()] == [[0, 2], [1]]
    np.testing.assert_array_equal(s.task_array("points", 0), np.arange(6.0).reshape(3, 2))
    np.testing.assert_array_equal(s.task_array("points", 1), np.ones((1, 2)))
    assert s.tasks[0] == {"id": "task-a", "instruction": "", "info": {"note": "x"}}
    assert s.tasks[1]["instruction"] == "pick up the bowl"
    assert s.config == {"a": 1}
    st = s.stats["obs"]
    assert st["min"] == [0.0, 0.0] and st["max"] == [2.0, 2.0]
    assert st["mean"][0] == pytest.approx((0 * 3 + 1 * 4 + 2 * 5) / 12)
    assert s["obs"].dtype == np.float32


def test_derived_keys_read_and_normalise_like_stored_ones(tmp_path, monkeypatch):
    import toy_reach

    class WithDerived(toy_reach.Reach):
        name, command = "test", "test"
        derived_keys = {"ends": ("state", (2, 0))}

    monkeypatch.setattr(registry, "BENCHMARKS", dict(registry.BENCHMARKS))
    monkeypatch.setattr(registry, "_LOADED", dict(registry._LOADED))
    path = tmp_path / "s.zarr"
    with EpisodeWriter(path, benchmark="test", chunk_steps=4) as w:
        w.add_task("t")
        for e in range(2):
            w.add_episode({"state": np.arange(12.0 * (e + 1)).reshape(-1, 3) + 100 * e}, 0)
    assert registry.open_store(path).keys == ["state"]  # no benchmark of that name yet: its stored keys alone
    registry.register_benchmark("test", WithDerived())
    store = registry.open_store(path)  # opened with the derived keys of the benchmark its header names
    assert store.keys == ["ends", "state"] and EpisodeStore(path).keys == ["state"]
    np.testing.assert_array_equal(store.array("ends"), store.array("state")[:, [2, 0]])
    np.testing.assert_array_equal(store.episode(1, ["ends"])["ends"], store.episode(1)["state"][:, [2, 0]])
    np.testing.assert_array_equal(store["ends"][2:5], store.array("state")[2:5, [2, 0]])
    np.testing.assert_array_equal(store["ends"].oindex[[1, 6]], store.array("state")[[1, 6]][:, [2, 0]])
    assert store["ends"].shape == (12, 2)
    full, ends = store.stats["state"], store.stats["ends"]
    assert ends["min"] == [full["min"][2], full["min"][0]] and ends["std"] == [full["std"][2], full["std"][0]]
    obs = with_derived(WithDerived.derived_keys, {"state": np.array([[1.0, 2.0, 3.0]])})
    np.testing.assert_array_equal(obs["ends"], [[3.0, 1.0]])
    assert with_derived({}, {"state": np.zeros(3)}).keys() == {"state"}
    assert pickle.loads(pickle.dumps(store)).keys == ["ends", "state"]  # a copy carries its derived keys
    missing = EpisodeStore(path, {"far": ("other", (0,)), "state": ("state", (0,))})
    assert missing.keys == ["state"]  # a derived key whose source the store lacks, or that it stores, is left out

    class BadDerived(WithDerived):
        derived_keys = {"bad": ("state", ())}

    with pytest.raises(ValueError, match="feature indices"):
        registry.register_benchmark("test", BadDerived())


def test_refuses_to_clobber_and_overwrites_atomically(tmp_path):
    path = tmp_path / "s.zarr"
    _write(path, episodes=1)
    with pytest.raises(StoreError, match="already exists"):
        _write(path)
    assert _write(path, episodes=3, overwrite=True).num_episodes == 3
    assert [p.name for p in tmp_path.iterdir()] == ["s.zarr"]


def test_interrupted_write_leaves_nothing(tmp_path):
    path = tmp_path / "s.zarr"
    with pytest.raises(KeyboardInterrupt), EpisodeWriter(path, benchmark="test") as w:
        w.add_task("t")
        w.add_episode({"x": np.zeros((5, 1))}, 0)
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_interrupted_overwrite_keeps_the_old_store(tmp_path):
    path = tmp_path / "s.zarr"
    _write(path, episodes=2)
    with pytest.raises(RuntimeError), EpisodeWriter(path, benchmark="test", overwrite=True) as w:
        w.add_task("t")
        raise RuntimeError("crash")
    assert EpisodeStore(path).num_episodes == 2


def test_incomplete_or_foreign_stores_do_not_load(tmp_path):
    path = tmp_path / "s.zarr"
    _write(path)
    meta = json.loads((path / "zarr.json").read_text())
    meta["attributes"]["complete"] = False
    (path / "zarr.json").write_text(json.dumps(meta))
    with pytest.raises(StoreError, match="incomplete"):
        EpisodeStore(path)
    meta["attributes"]["complete"] = True
    meta["attributes"]["version"] = 99
    (path / "zarr.json").write_text(json.dumps(meta))
    with pytest.raises(StoreError, match="version 99"):
        EpisodeStore(path)
    with pytest.raises(StoreError, match="no such store"):
        EpisodeStore(tmp_path / "missing.zarr")
    (tmp_path / "plain").mkdir()
    with pytest.raises(StoreError, match="not an episode store"):
        EpisodeStore(tmp_path / "plain")


def test_inconsistent_episodes_are_refused(tmp_path):
    with pytest.raises(StoreError, match="differ"), EpisodeWriter(tmp_path / "s.zarr", benchmark="t") as w:
        w.add_task("t")
        w.add_episode({"x": np.zeros((5, 1))}, 0)
        w.add_episode({"x": np.zeros((5, 2))}, 0)
    with pytest.raises(StoreError, match="no episodes"), EpisodeWriter(tmp_path / "e.zarr", benchmark="t"):
        pass


def _read_episode(args):
    store, index = args
    return store.episode(index)["obs"].sum()


def test_store_pickles_and_reads_from_worker_processes(tmp_path):
    s = _write(tmp_path / "s.zarr", episodes=6)
    s.episode(0)  # open a handle in the parent first
    clone = pickle.loads(pickle.dumps(s))
    assert clone.num_steps == s.num_steps
    with mp.get_context("spawn").Pool(2) as pool:
        sums = pool.map(_read_episode, [(s, i) for i in range(6)])
    assert sums == [float(s.episode(i)["obs"].sum()) for i in range(6)]


def test_a_store_is_reused_only_for_exactly_its_config(tmp_path):
    from dataclasses import dataclass
    from pathlib import Path

    from bpp.data.store import stored_with

    @dataclass(frozen=True)
    class Config:
        a: int = 1
        noise: float = 0.0
        files: tuple[Path, ...] = (Path("a.json"),)

    path = tmp_path / "s.zarr"
    with EpisodeWriter(path, benchmark="test", config={"a": 1, "noise": 0.0, "files": ["a.json"]}) as w:
        w.add_task("t")
        w.add_episode({"x": np.zeros((5, 1))}, 0)
    assert stored_with(path, Config()) is not None
    assert stored_with(path, Config(noise=0.2)) is None and stored_with(path, Config(a=2)) is None
    assert stored_with(path, Config(files=(Path("b.json"),))) is None
    assert stored_with(tmp_path / "missing.zarr", Config()) is None
    short = tmp_path / "short.zarr"  # a header that does not state every field is not this config
    with EpisodeWriter(short, benchmark="test", config={"a": 1}) as w:
        w.add_task("t")
        w.add_episode({"x": np.zeros((5, 1))}, 0)
    assert stored_with(short, Config()) is None


def _one_episode(path, benchmark, task_id, instruction="", **task_arrays):
    """A store of one two-step episode of one task, with `_write`'s keys and columns."""
    with EpisodeWriter(path, benchmark=benchmark, chunk_steps=4) as w:
        w.add_task(task_id, instruction=instruction, **task_arrays)
        steps = {"obs": np.zeros((2, 2), np.float32), "action": np.zeros((2, 1))}
        w.add_episode(steps, 0, angle=0.0, goal=np.zeros((2, 2), np.uint8))


def test_stores_merge_into_one_with_shared_tasks_joined(tmp_path):
    a = _write(tmp_path / "a.zarr")  # task-a: episodes 0, 2; task-b: episode 1
    with EpisodeWriter(tmp_path / "b.zarr", benchmark="test", config={"a": 2}, chunk_steps=4) as w:
        c = w.add_task("task-c", points=np.zeros((2, 2)))
        b = w.add_task("task-b", instruction="pick up the bowl", points=np.ones((1, 2)))
        w.add_episode(
            {"obs": np.full((2, 2), 7, np.float32), "action": np.zeros((2, 1))},
            c,
            angle=0.7,
            goal=np.zeros((2, 2), np.uint8),
        )
        w.add_episode(
            {"obs": np.full((5, 2), 8, np.float32), "action": np.ones((5, 1))},
            b,
            angle=0.8,
            goal=np.zeros((2, 2), np.uint8),
        )
    from bpp.cli import main

    main(["store", "merge", str(tmp_path / "a.zarr"), str(tmp_path / "b.zarr"), "--out", str(tmp_path / "m.zarr")])
    m = EpisodeStore(tmp_path / "m.zarr")
    assert [t["id"] for t in m.tasks] == ["task-a", "task-b", "task-c"]
    assert (m.num_episodes, m.num_steps) == (5, 12 + 7)
    assert [list(x) for x in m.task_episodes()] == [[0, 2], [1, 4], [3]]
    np.testing.assert_array_equal(m.episode(4)["obs"], np.full((5, 2), 8, np.float32))
    np.testing.assert_allclose(m.column("angle"), [0.0, 0.1, 0.2, 0.7, 0.8])
    np.testing.assert_array_equal(m.column("goal")[:, 0, 0], [0, 1, 2, 0, 0])
    np.testing.assert_array_equal(m.task_array("points", 2), np.zeros((2, 2)))
    assert m.stats["obs"]["max"] == [8.0, 8.0] and m.config == {"a": 1}
    assert [s["fingerprint"] for s in m.attrs["merged_from"]] == [
        a.fingerprint(),
        EpisodeStore(tmp_path / "b.zarr").fingerprint(),
    ]

    _one_episode(tmp_path / "c.zarr", "test", "task-b", instruction="pick up the plate", points=np.ones((1, 2)))
    differs = "task 'task-b' of .*c.zarr is another task than 'task-b' of .*a.zarr: its instruction"
    with pytest.raises(StoreError, match=f"{differs} \\('pick up the bowl', 'pick up the plate'\\) differs"):
        merge_stores([tmp_path / "a.zarr", tmp_path / "c.zarr"], tmp_path / "x.zarr")
    _one_episode(tmp_path / "d.zarr", "other", "t", points=np.ones((1, 2)))
    with pytest.raises(StoreError, match="a.zarr holds test data and .*d.zarr other data"):
        merge_stores([tmp_path / "d.zarr", tmp_path / "a.zarr"], tmp_path / "x.zarr")
    _one_episode(tmp_path / "e.zarr", "test", "task-e")  # no per-task arrays
    with pytest.raises(StoreError, match=r"e.zarr has per-task arrays \[\], .*a.zarr \['points'\]"):
        merge_stores([tmp_path / "a.zarr", tmp_path / "e.zarr"], tmp_path / "x.zarr")
    assert not (tmp_path / "x.zarr").exists()


def test_pieces_generated_with_different_seeds_merge_into_one_store(tmp_path):
    """The documented multi-machine workflow: each machine generates a piece with its own seed, then one merges."""
    pieces = [replace(PRESETS["debug"], num_tasks=2, demos_per_task=1, seed=seed) for seed in (0, 1)]
    paths = [generate(cfg, tmp_path / f"s{cfg.seed}.zarr", workers=1, progress=False).path for cfg in pieces]
    merged = merge_stores(paths, tmp_path / "all.zarr")
    ids = ["procedural-00000", "procedural-00001", "procedural-s1-00000", "procedural-s1-00001"]
    assert [t["id"] for t in merged.tasks] == ids and merged.num_episodes == 4
    assert [s["config"]["seed"] for s in merged.attrs["merged_from"]] == [0, 1]
    from bpp.data.store import stored_with

    assert stored_with(paths[0], pieces[0]) is not None
    assert stored_with(merged.path, pieces[0]) is None  # a merge holds more than its first piece's config makes

    other = replace(pieces[1], seed=0, procedural=replace(pieces[1].procedural, min_parts=5, max_parts=5))
    generate(other, tmp_path / "other.zarr", workers=1, progress=False)  # the same ids, other drawings
    refusal = "task 'procedural-00000' of .*other.zarr is another task than 'procedural-00000' of .*s0.zarr: its info"
    with pytest.raises(StoreError, match=refusal):
        merge_stores([paths[0], tmp_path / "other.zarr"], tmp_path / "x.zarr")
    assert not (tmp_path / "x.zarr").exists()


def _one_of_a_kind(path, obs=(2, np.float32), goal=(2, 2), config=None):
    """A store of one episode with `_write`'s keys and columns, its observation's width and dtype, goal's shape and
    config as given."""
    with EpisodeWriter(path, benchmark="test", config=config or {"a": 1}, chunk_steps=4) as w:
        w.add_task("task-z", points=np.ones((1, 2)))
        steps = {"obs": np.full((2, obs[0]), 9, obs[1]), "action": np.zeros((2, 1))}
        w.add_episode(steps, 0, angle=0.0, goal=np.zeros(goal, np.uint8))


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        (
            {"obs": (3, np.float32)},
            "per-step key 'obs' differs: rows of shape (3,) and dtype float32 in {b}, of shape (2,) and dtype float32 "
            "in {a}",
        ),
        ({"obs": (2, np.float64)}, "per-step key 'obs' differs: rows of shape (2,) and dtype float64 in {b}"),
        ({"goal": (3, 3)}, "episode column 'goal' differs: rows of shape (3, 3) and dtype uint8 in {b}"),
        ({"config": {"a": 1, "fps": 30}}, "config entry 'fps' differs: 30 in {b}, nothing in {a}"),
    ],
    ids=["a key's shape", "a key's dtype", "a column's shape", "the control rate"],
)
def test_stores_of_different_kinds_are_refused_naming_the_field(tmp_path, kind, message):
    a, b = _write(tmp_path / "a.zarr").path, tmp_path / "b.zarr"
    _one_of_a_kind(b, **kind)
    with pytest.raises(StoreError, match=re.escape(message.format(a=a, b=b))):
        merge_stores([a, b], tmp_path / "x.zarr")
    _one_of_a_kind(tmp_path / "c.zarr", config={"a": 2, "seed": 7})  # other generation settings: one kind still
    assert merge_stores([a, tmp_path / "c.zarr"], tmp_path / "ac.zarr").num_episodes == 4


def test_stores_refuse_non_finite_numbers_and_training_refuses_a_store_that_holds_them(tmp_path, monkeypatch):
    """The store's door refuses NaN and infinities from any writer (generators, importers, merges); a store written
    before it did is refused by training before anything is built."""
    good = {"state": np.zeros((4, 2), np.float32), "action": np.zeros((4, 2), np.float32)}
    bad = {**good, "action": np.array([[0, 0], [0, 0], [0, np.nan], [0, 0]], np.float32)}
    writer = EpisodeWriter(tmp_path / "s.zarr", benchmark="drawanything")
    writer.add_task("t")
    writer.add_episode(good, 0)
    with pytest.raises(StoreError, match=r"episode 1: 'action' holds nan at step 2 \(item 1\); a store keeps finite"):
        writer.add_episode(bad, 0)
    with pytest.raises(StoreError, match=r"'state' holds -inf at step 0 \(item 0\)"):
        writer.add_episode({**good, "state": np.full((4, 2), -np.inf, np.float32)}, 0)
    writer.add_episode({**good, "state": np.ones((4, 2), np.float32)}, 0)
    finite_statistics(writer.close())  # the refused episodes left nothing behind

    monkeypatch.setattr(store_module, "_check_finite", lambda *args: None)  # a store from before the door
    with EpisodeWriter(tmp_path / "old.zarr", benchmark="drawanything") as old:
        old.add_task("t")
        old.add_episode(good, 0)
        old.add_episode(bad, 0)
    with pytest.raises(UserError, match=r"old.zarr: the (min|mean) of 'action' is not finite"):
        finite_statistics(EpisodeStore(tmp_path / "old.zarr"))
