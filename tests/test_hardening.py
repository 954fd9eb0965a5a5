"""Inputs a careful user or an attacker might give: refused with a message naming the input, or handled safely.

These test the library's checks; test_hardening_probes.py gives the same kinds of inputs to the command line."""

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import bpp.train
from bpp.benchmarks.draw.dataset import PRESETS, generate
from bpp.checkpoint import _remove_stale_temporaries
from bpp.errors import UserError
from bpp.executor import _check_reachable
from bpp.train import TrainConfig, train
from helpers import config


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("grad_clip", -1.0),
        ("grad_clip", 0.0),
        ("ema_decay", 1.0),
        ("ema_decay", -0.1),
        ("save_every", 0),
        ("log_every", 0),
        ("lr", 0.0),
        ("warmup_steps", -1),
        ("tasks_per_batch", 0),
        ("workers", -2),
        ("frame_cache_gb", -1.0),
    ],
)
def test_training_settings_out_of_range_are_refused_naming_the_field(field, value):
    with pytest.raises(ValueError, match=rf"^{field} must be .*got {value!r}"):
        TrainConfig(data=Path("x.zarr"), **{field: value})


@pytest.mark.slow
def test_resume_refuses_settings_other_than_the_runs_own(debug_store, tmp_path):
    from dataclasses import replace

    cfg = TrainConfig(data=debug_store.path, out=tmp_path / "run", steps=2, batch_size=4, workers=0, warmup_steps=1)
    train(cfg, config("bpp"), progress=False)
    resume = replace(cfg, resume=True)
    for changed, model, field in (
        (replace(resume, seed=1), config("bpp"), "train_config.seed: 0 in the run, 1 now"),
        (replace(resume, steps=4), config("bpp"), "train_config.steps: 2 in the run, 4 now"),
        (resume, config("bpp", dim=64, heads=2), "model_config.dim: 32 in the run, 64 now"),
        (replace(resume, compile="default"), config("bpp"), "train_config.compile: 'off' in the run, 'default' now"),
    ):
        with pytest.raises(ValueError, match=field):
            train(changed, model, progress=False)
    before = (tmp_path / "run" / "config.json").read_text()
    train(resume, config("bpp"), progress=False)  # the same settings: resumes (nothing left to do)
    assert (tmp_path / "run" / "config.json").read_text() == before
    record = json.loads(before)  # a run started before bpp had a field: its record lacks it
    del record["model_config"]["prompt"]["rollout_memory"]
    (tmp_path / "run" / "config.json").write_text(json.dumps(record))
    train(resume, config("bpp"), progress=False)  # read at the field's default: the same settings
    memory = config("bpp", prompt=replace(config("bpp").prompt, rollout_memory=2))
    with pytest.raises(ValueError, match="model_config.prompt.rollout_memory: 0 in the run, 2 now"):
        train(resume, memory, progress=False)


@pytest.mark.slow
def test_overwrite_replaces_only_a_store(tmp_path, debug_store):
    from bpp.benchmarks.draw.dataset import PRESETS, generate
    from bpp.data.integrity import StoreError
    from bpp.data.store import EpisodeStore

    precious = tmp_path / "thesis"
    precious.mkdir()
    (precious / "chapter1.tex").write_text("years of work")
    with pytest.raises(StoreError, match="is not an episode store; only a store is ever replaced"):
        generate(PRESETS["debug"], precious, workers=1, overwrite=True, progress=False)
    assert (precious / "chapter1.tex").read_text() == "years of work"
    store = tmp_path / "store.zarr"
    generate(PRESETS["debug"], store, workers=1, progress=False)
    again = generate(PRESETS["debug"], store, workers=1, overwrite=True, progress=False)  # a store is replaced
    assert EpisodeStore(again.path).num_tasks == debug_store.num_tasks


def test_interrupted_writers_leave_no_hidden_folders_behind(tmp_path):
    import os

    from bpp.benchmarks.draw.dataset import PRESETS, generate

    store = tmp_path / "d.zarr"
    finished = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead = tmp_path / f".d.zarr.partial-{int(finished.stdout)}-0123abcd"  # a writer that was killed
    alive = tmp_path / f".d.zarr.partial-{os.getpid()}-4567ef01"  # a writer still running (this process)
    for folder in (dead, alive):
        folder.mkdir()
    generate(PRESETS["debug"], store, workers=1, progress=False)
    assert not dead.exists() and alive.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([alive.name, "d.zarr"])


def test_only_ascii_digits_are_read_as_numbers(tmp_path):
    """A process id in a temporary's name, a port: other Unicode digits (which str.isdigit and a regex's \\d accept,
    and int() reads or refuses) are no number, so no file is taken for a dead process's and no port is parsed."""
    nines = "\u0669" * 9  # Arabic-Indic digits: int() reads 999999999, a process that does not run
    stale = tmp_path / ".x.partial-999999999-0123abcd"
    kept = [tmp_path / f".x.partial-{nines}-0123abcd", tmp_path / f".last.tmp-{nines}"]
    for folder in [stale, *kept]:
        folder.mkdir()
    _remove_stale_temporaries(tmp_path)
    assert not stale.exists() and all(folder.exists() for folder in kept)
    for port in ("\u00b2", "\u0668\u0660"):  # superscript two (int() refuses it), Arabic-Indic 80
        assert _check_reachable(f"127.0.0.1:{port}", timeout=1.0) is None  # not host:port: left to Ray


@pytest.mark.slow
def test_runs_with_a_damaged_newest_checkpoint_resume_from_the_newest_intact_one(debug_store, tmp_path, capsys):
    from dataclasses import replace

    run = tmp_path / "run"
    cfg = TrainConfig(data=debug_store.path, out=run, steps=4, batch_size=4, workers=0, warmup_steps=1, save_every=2)
    train(cfg, config("bpp"), progress=False)
    checkpoints = run / "checkpoints"
    weights = checkpoints / "step_00000004" / "ema.safetensors"
    weights.write_bytes(weights.read_bytes()[:1000])  # truncated, as by a full disk
    capsys.readouterr()
    more = replace(cfg, resume=True)
    train(more, config("bpp"), progress=False)  # the run's own settings: resumes from step 2, saves step 4 again
    err = capsys.readouterr().err
    assert "skipping step_00000004" in err and "ema.safetensors: unreadable weights" in err
    assert "resuming from step_00000002" in err
    (checkpoints / "last").write_text("step_00000009")  # a pointer to a folder that is gone
    from bpp.checkpoint import read_state, resolve_checkpoint

    assert resolve_checkpoint(run).name == "step_00000004"
    assert "names step_00000009, which is missing" in capsys.readouterr().err
    (checkpoints / "step_00000004" / "state.json").write_text('{"format": "bpp-check')  # truncated JSON
    with pytest.raises(ValueError, match="state.json: the checkpoint state is not valid JSON"):
        read_state(checkpoints / "step_00000004")


def test_training_warns_when_demonstrations_are_longer_than_the_model_s_prompts(debug_store, tmp_path, capsys):
    from dataclasses import replace

    cfg = TrainConfig(data=debug_store.path, out=tmp_path / "a", steps=1, batch_size=4, workers=0, warmup_steps=1)
    train(cfg, config("bpp"), progress=False)
    assert "warning" not in capsys.readouterr().out  # the debug store's demonstrations fit 800 steps
    short = config("bpp")
    short = replace(short, prompt=replace(short.prompt, max_steps=20))
    train(replace(cfg, out=tmp_path / "b"), short, progress=False)
    episodes = debug_store.num_episodes
    assert f"of the store's {episodes} demonstrations are longer than this model's prompts (20 steps" in (
        capsys.readouterr().out
    )


@pytest.mark.slow
def test_eval_reuses_results_only_for_the_same_weights_and_task_content(debug_store, tmp_path, capsys):
    import shutil

    from bpp.core.registry import get_benchmark
    from bpp.evaluation.evaluate import Protocol, evaluate

    benchmark = get_benchmark("drawanything")
    run, out, drawing = tmp_path / "run", tmp_path / "eval", tmp_path / "d.json"

    def write_drawing(apex: float) -> None:
        drawing.write_text(json.dumps({"drawings": [{"id": "v", "strokes": [[[0.2, 0.2], [0.5, apex], [0.8, 0.2]]]}]}))

    def train_run(seed: int) -> None:
        shutil.rmtree(run, ignore_errors=True)
        cfg = TrainConfig(data=debug_store.path, out=run, steps=1, batch_size=4, workers=0, warmup_steps=1, seed=seed)
        train(cfg, config("bpp"), progress=False)

    def eval_once() -> bool:
        capsys.readouterr()
        task_set = benchmark.task_set_from_files([drawing], tmp_path / "data")
        evaluate(run, task_set, [0], out, Protocol(rollouts=1, max_steps=6), workers=1, videos=0, progress=False)
        return "reusing" in capsys.readouterr().out

    write_drawing(0.8)
    train_run(0)
    assert not eval_once() and eval_once()  # the same weights, file and protocol: reused
    write_drawing(0.7)  # the drawing file edited at the same path
    assert not eval_once() and eval_once()
    train_run(1)  # the run trained again into the same folder
    assert not eval_once()


@pytest.mark.parametrize(
    ("point", "shown"),
    [(["0.5", 0.2], "['0.5', 0.2]"), ([True, 0.2], "[True, 0.2]"), ([0.5, None], "[0.5, None]"), (0.5, "0.5")],
)
def test_drawing_coordinates_must_be_json_numbers(tmp_path, point, shown):
    from bpp.drawing.drawing import DrawingError
    from bpp.drawing.files import load_drawings

    path = tmp_path / "d.json"
    path.write_text(json.dumps({"drawings": [{"id": "a", "strokes": [[[0.1, 0.1], point]]}]}))
    with pytest.raises(DrawingError, match="stroke 0, point 1: expected \\[x, y\\] with two numbers") as err:
        load_drawings(path)
    assert str(path) in str(err.value) and shown in str(err.value)


def test_deeply_nested_json_is_refused_naming_the_file(tmp_path, debug_store):
    from bpp.checkpoint import read_state
    from bpp.drawing.drawing import DrawingError
    from bpp.drawing.files import load_drawings

    deep = "[" * 100_000 + "]" * 100_000
    drawing = tmp_path / "deep.json"
    drawing.write_text('{"drawings": ' + deep + "}")
    with pytest.raises(DrawingError, match="deep.json: the drawing file is nested too deeply"):
        load_drawings(drawing)
    ckpt = tmp_path / "step_00000001"
    ckpt.mkdir()
    (ckpt / "state.json").write_text(deep)
    with pytest.raises(ValueError, match="state.json: the checkpoint state is nested too deeply"):
        read_state(ckpt)


def test_svg_transforms_are_applied_in_document_order(tmp_path):
    import numpy as np

    from bpp.drawing.files import load_drawings

    def svg(body: str) -> Path:
        path = tmp_path / f"s{len(list(tmp_path.iterdir()))}.svg"
        path.write_text(f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 200 200">{body}</svg>')
        return path

    transformed = svg(
        '<g transform="translate(100,20) rotate(90)"><path d="M 0 0 L 10 0" transform="scale(2)"/>'
        '<line x1="0" y1="0" x2="0" y2="30"/></g><polyline points="10,10 40,10" transform="translate(5,100)"/>'
    )
    plain = svg('<path d="M 100 20 L 100 40"/><line x1="100" y1="20" x2="70" y2="20"/><path d="M 15 110 L 45 110"/>')
    a, b = load_drawings([transformed])[0], load_drawings([plain])[0]
    assert len(a.strokes) == len(b.strokes) == 3
    for p, q in zip(a.strokes, b.strokes, strict=True):
        np.testing.assert_allclose(p, q, atol=1e-9)


@pytest.mark.slow
def test_any_drawing_file_is_read_and_demonstrated_in_bounded_time(tmp_path):
    import time

    import numpy as np

    from bpp.benchmarks.draw.demonstrator import demonstrate
    from bpp.drawing.drawing import DrawingError
    from bpp.drawing.files import MAX_POINTS, MAX_STROKES, load_drawings

    def json_file(name, strokes):
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps({"drawings": [{"id": name, "strokes": strokes}]}))
        return path

    t = np.linspace(0, 2 * np.pi, 200_000)
    circle = json_file("circle", [np.stack([0.5 + 0.4 * np.cos(t), 0.5 + 0.4 * np.sin(t)], 1).tolist()])
    many = json_file("many", [[[0.1, 0.1], [0.2, 0.2]]] * 20_000)
    long_ink = json_file("long", [[[float(j % 2), 0.1 + 0.8 * k / 99] for j in range(49)] for k in range(100)])
    zigzag = tmp_path / "zigzag.svg"
    points = " ".join(f"{i * 0.05:.2f},{(i % 2) * 100}" for i in range(20_000))
    zigzag.write_text(f'<svg xmlns="http://www.w3.org/2000/svg"><polyline points="{points}"/></svg>')
    start = time.perf_counter()
    loaded = load_drawings(circle)[0]  # 200k points, closer than MIN_POINT_SPACING: merged, the shape kept
    assert 2000 < sum(map(len, loaded.strokes)) <= MAX_POINTS
    demonstrate(loaded, 0.3, np.array([100.0, 100.0]), np.random.default_rng(0))
    with pytest.raises(DrawingError, match=f"many.json: drawing 'many' has 20000 strokes; .* at most {MAX_STROKES}"):
        load_drawings(many)
    with pytest.raises(DrawingError, match=f"zigzag.svg has 20000 points .* at most {MAX_POINTS}"):
        load_drawings(zigzag)
    with pytest.raises(DrawingError, match="drawing 'long': drawing it takes more than 1200 steps"):
        demonstrate(load_drawings(long_ink)[0], 0.3, np.array([100.0, 100.0]), np.random.default_rng(0))
    assert time.perf_counter() - start < 60  # each took minutes before (quadratic corners, uncapped sampling)


def test_corner_detection_matches_its_definition(rng):
    import numpy as np

    from bpp.benchmarks.draw.demonstrator import _corner_arclengths

    def by_definition(points, angle_deg, scale):  # vertex by vertex, as documented (quadratic time)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
        corners = []
        for i in range(1, len(points) - 1):
            back = points[i] - np.array([np.interp(s[i] - scale, s, points[:, k]) for k in range(2)])
            ahead = np.array([np.interp(s[i] + scale, s, points[:, k]) for k in range(2)]) - points[i]
            nb, na = np.linalg.norm(back), np.linalg.norm(ahead)
            if nb < 1e-9 or na < 1e-9:
                continue
            turn = np.degrees(np.arccos(np.clip(back @ ahead / (nb * na), -1.0, 1.0)))
            if turn > angle_deg and (not corners or s[i] - corners[-1] > scale):
                corners.append(s[i])
        return corners

    for _ in range(30):
        points = np.cumsum(rng.normal(0, 15, (int(rng.integers(3, 200)), 2)), axis=0)
        for scale in (8.0, 20.0):
            np.testing.assert_allclose(_corner_arclengths(points, 50.0, scale), by_definition(points, 50.0, scale))


def test_damaged_stores_are_named_with_the_damaged_part(tmp_path, debug_store):
    import shutil

    from bpp.data.integrity import StoreError
    from bpp.data.store import EpisodeStore

    header, chunk = tmp_path / "header.zarr", tmp_path / "chunk.zarr"
    shutil.copytree(debug_store.path, header)
    shutil.copytree(debug_store.path, chunk)
    (header / "zarr.json").write_text('{"zarr_format": 3, "node_type": "group", "attributes": {')
    with pytest.raises(StoreError, match="header.zarr: damaged store header"):
        EpisodeStore(header)
    part = next(p for p in sorted((chunk / "data" / "action" / "c").rglob("*")) if p.is_file())
    part.write_bytes(part.read_bytes()[:20])
    with pytest.raises(StoreError, match="chunk.zarr: damaged store, cannot read data/action"):
        EpisodeStore(chunk).array("action")


@pytest.mark.parametrize("angle", [0.3, -0.7, 1.0, -np.pi / 4])
def test_identical_integer_drawings_score_exactly_zero_at_any_angle(angle, rng):
    from bpp.drawing.geometry import BOARD_CENTER, canvas_to_upright, rotation
    from bpp.drawing.metric import chamfer_distance, ink_mask

    line = np.array([[x, 256] for x in range(156, 357, 10)], float)
    polylines = [line, *(rng.integers(100, 412, (int(rng.integers(2, 30)), 2)).astype(float) for _ in range(20))]
    for points in polylines:
        on_board = (points - BOARD_CENTER) @ rotation(angle).T + BOARD_CENTER  # as a rollout inks it
        assert chamfer_distance(ink_mask([points]), ink_mask([canvas_to_upright(on_board, angle)])) == 0.0


@pytest.mark.parametrize(
    ("make", "field"),
    [
        ("DemoConfig(noise_std=-1.0)", "noise_std"),
        ("DemoConfig(max_steps=0)", "max_steps"),
        ("DemoConfig(speed_range=(0.0, 0.0))", "speed_range"),
        ("ProceduralConfig(min_parts=7, max_parts=6)", "max_parts"),
        ("ProceduralConfig(max_parts=10**9)", "max_parts"),
        ("ProceduralConfig(min_new_point_px=1000.0)", "min_new_point_px"),
        ("ProceduralConfig(oval_axis_px=(-1.0, 5.0))", "oval_axis_px"),
        ("DrawDataConfig(demos_per_task=0)", "demos_per_task"),
        ("DrawDataConfig(seed=-1)", "seed"),
        ("Protocol(seed=-1)", "seed"),
        ("Protocol(rollouts=0)", "rollouts"),
        ("DiffusionConfig(num_inference_steps=0)", "num_inference_steps"),
        ("DiffusionConfig(down_dims=(50,))", "down_dims"),
        ("DiffusionConfig(kernel_size=4)", "kernel_size"),
        ("ObsConfig(image_widths=(50,), image_blocks=(1,))", "image_widths"),
        ("ObsConfig(image_size=100_000)", "image_size"),
        ("Horizons(n_obs_steps=0)", "n_obs_steps"),
        ("BPPConfig(heads=3)", "heads"),
        ("BPPConfig(dropout=1.5)", "dropout"),
        ("BPPConfig(horizons=Horizons(horizon=15, n_action_steps=8))", "horizon"),
        ("ICRTConfig(layers=0)", "layers"),
    ],
)
def test_every_config_refuses_values_out_of_range_naming_the_field(make, field):
    from bpp.benchmarks.draw.dataset import DrawDataConfig  # noqa: F401 - used by eval below
    from bpp.benchmarks.draw.demonstrator import DemoConfig  # noqa: F401
    from bpp.drawing.procedural import ProceduralConfig  # noqa: F401
    from bpp.evaluation.evaluate import Protocol  # noqa: F401
    from bpp.policies.bpp.config import BPPConfig  # noqa: F401
    from bpp.policies.config import DiffusionConfig, Horizons, ObsConfig  # noqa: F401
    from bpp.policies.icrt.config import ICRTConfig  # noqa: F401

    with pytest.raises(ValueError, match=rf"{field}"):
        eval(make)


def test_damaged_store_tables_and_missing_episodes_name_the_store(tmp_path, debug_store):
    import shutil

    from bpp.data.integrity import StoreError
    from bpp.data.store import EpisodeStore

    store = tmp_path / "no-ends.zarr"
    shutil.copytree(debug_store.path, store)
    shutil.rmtree(store / "meta" / "episode_ends")
    with pytest.raises(StoreError, match="no-ends.zarr: damaged store \\(no meta/episode_ends\\)"):
        EpisodeStore(store)
    with pytest.raises(IndexError, match=f"{debug_store.path}: episode 99999 out of range"):
        debug_store.episode(99999)


@pytest.mark.parametrize(
    ("device", "said"),
    [
        ("potato", "not a device; expected auto, cpu, cuda or cuda:N"),
        ("mps", "bpp runs on cpu or cuda"),
        ("cuda:99", "CUDA GPU"),
    ],
)
def test_a_device_this_machine_lacks_is_refused_before_any_work(debug_store, tmp_path, device, said):
    import torch

    from bpp.errors import UserError

    if device.startswith("cuda") and torch.cuda.device_count() > 99:
        pytest.skip("a machine with 100 GPUs")
    cfg = TrainConfig(data=debug_store.path, out=tmp_path / "run", method="bpp", steps=1, batch_size=4, device=device)
    with pytest.raises(UserError, match=f"--device {device}.*{said}"):
        train(cfg, config("bpp"), progress=False)
    assert not (tmp_path / "run").exists()


def test_the_device_auto_and_cpu_resolve_to_a_device_torch_has():
    import torch

    from bpp.utils import resolve_device

    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")


def test_a_store_with_one_demonstration_per_task_is_refused_before_the_model_is_built(tmp_path, monkeypatch):
    cfg = replace(PRESETS["debug"], num_tasks=3, demos_per_task=1)
    store = generate(cfg, tmp_path / "single.zarr", workers=1, progress=False)

    def built(*args, **kwargs):
        raise AssertionError("the model was built before the store was checked")

    monkeypatch.setattr(bpp.train, "build_training", built)
    run = TrainConfig(data=store.path, out=tmp_path / "run", method="bpp", steps=1, batch_size=4)
    with pytest.raises(UserError, match="the most any task has is 1.*--demos-per-task 2"):
        train(run, config("bpp"), progress=False)
    assert not (tmp_path / "run").exists()


def test_a_store_without_a_key_the_policy_uses_is_refused_before_the_model_is_built(debug_store, tmp_path, monkeypatch):
    """A store generated before a key was added (LIBERO's action_abs, draw3d's target_in_canvas) is named with what
    it lacks and what to do, not reported later as missing normalisation statistics."""

    def built(*args, **kwargs):
        raise AssertionError("the model was built before the store was checked")

    monkeypatch.setattr(bpp.train, "build_training", built)
    run = TrainConfig(data=debug_store.path, out=tmp_path / "run", method="bpp", steps=1, batch_size=4)
    with pytest.raises(UserError, match=r"acts with \['action_abs'\], which the store lacks.*generate it again"):
        train(run, config("bpp", action_key="action_abs"), progress=False)
    assert not (tmp_path / "run").exists()
