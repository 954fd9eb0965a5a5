"""Frames rendered on the training device from references (``bpp train --frames-on device``) must be exactly the
frames the loader renders: the renderer itself, whole batches of every method, and training."""

from dataclasses import replace

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.benchmarks.draw.dataset import render_episode_steps
from bpp.benchmarks.draw.device_render import DrawFrameTable
from bpp.core.contract import device_frames
from bpp.data.frame_refs import DeviceFrames, render_batch
from bpp.data.prompt_dataset import PromptBatchDataset
from bpp.errors import UserError
from bpp.policies.registry import get_method
from bpp.train import TrainConfig, batch_loader, train
from helpers import DRAW_FRAMES, assert_same_batches, config, obs_config

IMAGE_OBS = obs_config(
    image_keys=("image",), image_size=24, image_features=16, image_widths=(8, 16), image_blocks=(1, 1)
)


@pytest.fixture(scope="module")
def table(debug_store):
    return DrawFrameTable(debug_store)


@pytest.mark.parametrize("size", [16, 64, 224])
def test_the_table_renders_the_numpy_renderer_s_frames_exactly(debug_store, table, rng, size):
    refs, expected = [], []
    for episode in rng.choice(len(debug_store.episode_starts), 5, replace=False):
        length = int(debug_store.episode_ends[episode] - debug_store.episode_starts[episode])
        steps = rng.integers(0, length + 1, 8)  # any order, repeats, and the frame after the last step
        steps[:2] = 0, length
        refs += [(episode + 1, s) for s in steps]
        expected.append(render_episode_steps(debug_store, int(episode), size, steps))
    refs.insert(3, (0, 0))  # a blank
    expected = np.concatenate(expected)
    expected = np.concatenate([expected[:3], np.zeros((1, size, size, 3), np.uint8), expected[3:]])
    frames = table.render(torch.tensor(refs), size)
    assert frames.dtype == torch.uint8 and frames.shape == (len(refs), size, size, 3)
    np.testing.assert_array_equal(frames.numpy(), expected)
    assert expected[5].any() and (expected[5] != expected[4]).any()  # frames with ink and a cursor, not all alike


def test_the_table_refuses_what_it_cannot_render(debug_store, table):
    length = int(debug_store.episode_ends[0])
    with pytest.raises(IndexError, match="out of range"):
        table.render(torch.tensor([[1, length + 1]]), 16)
    with pytest.raises(IndexError, match="out of range"):
        table.render(torch.tensor([[len(debug_store.episode_starts) + 1, 0]]), 16)
    with pytest.raises(ValueError, match="at least 8"):
        table.render(torch.tensor([[1, 0]]), 4)
    assert not table.render(torch.zeros((2, 2), dtype=torch.int64), 16).any()


def test_the_benchmarks_say_whether_they_render_on_a_device(debug_store):
    assert isinstance(device_frames(BENCHMARK, debug_store, "cpu"), DeviceFrames)
    import toy_reach  # a plug-in benchmark that renders in its loader only

    with pytest.raises(ValueError, match="--frames-on loader"):
        device_frames(toy_reach.BENCHMARK, debug_store, "cpu")


def _spec(store, method: str):
    cfg = config(method)
    if method != "goal_image":  # Goal-Image observes the state and is conditioned on a goal frame
        cfg = replace(cfg, obs=IMAGE_OBS)
    return get_method(method).model_cls(cfg, store.stats).data_spec()


@pytest.mark.parametrize(("method", "pad"), [("bpp", 0), ("bpp", 100), ("goal_image", 0), ("icrt", 0), ("icrt", 50)])
def test_batches_of_references_render_to_the_batches_of_frames(debug_store, table, method, pad):
    spec = _spec(debug_store, method)
    kw = dict(batch_size=8, seed=3, tasks_per_batch=2, pad_to_multiple=pad)
    frames = PromptBatchDataset(debug_store, spec, frames=DRAW_FRAMES, **kw)
    refs = PromptBatchDataset(debug_store, spec, frames=DRAW_FRAMES, frame_refs=True, **kw)
    for i in range(3):
        plain, referenced = frames[i], refs[i]
        key = "image" if method == "goal_image" else None
        small = referenced["context"][key] if key else referenced["obs"]["image"]
        assert small.dtype == np.int64 and small.shape[-1] == 2  # references, not frames
        assert_same_batches(plain, render_batch(referenced, spec, table), f"{method} batch {i}")


@pytest.mark.parametrize("method", ["bpp", "goal_image"])
def test_a_camera_the_table_cannot_render_is_refused(debug_store, table, method):
    fields = {"obs": replace(IMAGE_OBS, image_keys=("board_image",))}
    if method == "goal_image":
        fields.update(goal_camera="board_image", goal_image_size=IMAGE_OBS.image_size)
    cfg = replace(config(method), **fields)
    spec = get_method(method).model_cls(cfg, debug_store.stats).data_spec()
    batch = PromptBatchDataset(debug_store, spec, frames=DRAW_FRAMES, batch_size=4, seed=3, frame_refs=True)[0]
    with pytest.raises(UserError, match="board_image.*--frames-on loader"):
        render_batch(batch, spec, table)


def test_references_built_in_loader_processes_render_to_the_same_batches(debug_store, table):
    spec = _spec(debug_store, "bpp")
    here = PromptBatchDataset(debug_store, spec, frames=DRAW_FRAMES, batch_size=8, seed=3)
    there = PromptBatchDataset(debug_store, spec, frames=DRAW_FRAMES, batch_size=8, seed=3, frame_refs=True)
    for i, batch in enumerate(batch_loader(there, range(3), workers=2, pin_memory=False)):
        assert_same_batches(here[i], render_batch(batch, spec, table), f"batch {i}")


@pytest.mark.slow
def test_training_with_frames_rendered_on_the_device_is_training_with_the_loader_s(debug_store, tmp_path):
    weights = {}
    for frames_on in ("loader", "device"):
        cfg = TrainConfig(
            data=debug_store.path,
            out=tmp_path / frames_on,
            steps=3,
            batch_size=8,
            tasks_per_batch=2,
            save_every=3,
            workers=0,
            warmup_steps=1,
            frames_on=frames_on,
            device="cpu",  # bit for bit: a GPU's atomics would make even two identical runs differ
        )
        run = train(cfg, replace(config("bpp"), obs=IMAGE_OBS), progress=False)
        weights[frames_on] = load_file(run / "model.safetensors")
    assert weights["loader"].keys() == weights["device"].keys()
    for k, v in weights["loader"].items():
        torch.testing.assert_close(weights["device"][k], v, rtol=0, atol=0, msg=k)
    with pytest.raises(ValueError, match="frames_on"):
        TrainConfig(data=debug_store.path, frames_on="gpu")


@pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device (bench/gpu_throughput_and_tests.sh runs it on one)"
)
@pytest.mark.parametrize("size", [64, 224])
def test_on_a_gpu_the_frames_are_the_cpu_s_but_for_a_level_at_the_cursor_s_rim(debug_store, table, size):
    refs = []
    for episode in range(0, len(debug_store.episode_starts), 5):
        length = int(debug_store.episode_ends[episode] - debug_store.episode_starts[episode])
        refs += [(episode + 1, s) for s in range(0, length + 1, 3)]
    refs = torch.tensor(refs)
    here = table.render(refs, size).numpy().astype(int)
    there = DrawFrameTable(debug_store, "cuda").render(refs, size).cpu().numpy().astype(int)
    differ = np.abs(here - there)
    assert differ.max() <= 1 and (differ > 0).mean() < 1e-4, f"{(differ > 0).sum()} values differ, by {differ.max()}"
