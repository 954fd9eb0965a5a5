"""The GPU-speed changes must not change what trains: selective frame rendering, prompts with one observation per
chunk and the paper encoder's ResNet stem; and the image encoder must not crash a multi-threaded CPU."""

import os
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
import torch

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.data.contexts import batch_context, task_context
from bpp.data.prompt_dataset import PromptBatchDataset
from bpp.nn.vision import ResNetGN
from bpp.policies.config import ObsConfig
from bpp.policies.registry import get_method
from bpp.utils import to_torch
from helpers import DRAW_FRAMES, assert_same_batches, config, obs_config

IMAGE_OBS = obs_config(
    image_keys=("image",), image_size=24, image_features=16, image_widths=(8, 16), image_blocks=(1, 1)
)


def _bpp(store, relative_to: str = "", **prompt):
    cfg = replace(config("bpp"), obs=IMAGE_OBS, action_relative_to=relative_to)
    cfg = replace(cfg, prompt=replace(cfg.prompt, **prompt))
    torch.manual_seed(0)
    return get_method("bpp").model_cls(cfg, store.stats).eval()


def test_batches_rendering_only_their_frames_equal_those_from_whole_episodes(debug_store):
    spec = _bpp(debug_store).data_spec()
    assert spec.context_obs_stride == 10
    whole = PromptBatchDataset(debug_store, spec, frames=DRAW_FRAMES, batch_size=8, seed=3, frame_cache_bytes=1 << 30)
    selective = PromptBatchDataset(debug_store, spec, frames=DRAW_FRAMES, batch_size=8, seed=3, frame_cache_bytes=0)
    assert whole.whole_episodes and not selective.whole_episodes
    for i in range(3):
        a, b = whole[i], selective[i]
        assert_same_batches(a, b)
    assert len(selective._frame_cache) == 0 and len(whole._frame_cache) > 0


def test_the_frames_of_a_policy_that_observes_cameras_come_from_the_store_s_benchmark(debug_store):
    """The data layer knows no benchmark: a dataset for a policy that observes cameras is given their source."""
    with pytest.raises(ValueError, match=r"camera frames \(image\): pass `frames`.*drawanything"):
        PromptBatchDataset(debug_store, _bpp(debug_store).data_spec())


def test_batches_built_in_loader_processes_equal_those_built_here(debug_store):
    """`bpp train`'s loader processes (`batch_loader`) must hand over the very batches the dataset builds here."""
    from bpp.train import batch_loader

    spec = _bpp(debug_store).data_spec()
    for cache in (0, 1 << 30):  # each batch's frames, and whole episodes kept
        here = PromptBatchDataset(debug_store, spec, frames=DRAW_FRAMES, batch_size=8, seed=3, frame_cache_bytes=cache)
        there = PromptBatchDataset(debug_store, spec, frames=DRAW_FRAMES, batch_size=8, seed=3, frame_cache_bytes=cache)
        arrived = list(batch_loader(there, range(4), workers=2, pin_memory=False))
        assert isinstance(arrived[0]["obs"]["image"], torch.Tensor)
        assert here[0]["obs"]["image"].dtype == np.uint8 and here[0]["obs"]["image"].any()
        for i, batch in enumerate(arrived):
            assert_same_batches(here[i], batch, f"batch {i}, cache {cache}")


@pytest.mark.parametrize("relative_to", ["", "agent_pos"])
def test_a_prompt_with_one_observation_per_chunk_encodes_like_the_whole_prompt(debug_store, relative_to):
    model = _bpp(debug_store, relative_to)
    spec = model.data_spec()
    full = batch_context("demo", task_context(debug_store, 5, spec, BENCHMARK.frames))
    strided = batch_context("demo", task_context(debug_store, 5, spec, BENCHMARK.frames, obs_stride=10))
    steps = full["action"].shape[1]
    assert strided["obs"]["image"].shape[1] == -(-steps // 10) and strided["obs_stride"].tolist() == [10]
    np.testing.assert_array_equal(strided["obs"]["image"], full["obs"]["image"][:, ::10])
    with torch.no_grad():
        a = model.encode_prompt(to_torch(full, "cpu"))
        b = model.encode_prompt(to_torch(strided, "cpu"))
    assert torch.equal(a.tokens, b.tokens) and torch.equal(a.valid, b.valid)


def test_training_batches_carry_strided_prompts_and_train(debug_store):
    model = _bpp(debug_store).train()
    batch = PromptBatchDataset(
        debug_store, model.data_spec(), frames=DRAW_FRAMES, batch_size=8, seed=0, tasks_per_batch=2
    )[0]
    context = batch["context"]
    assert context["obs"]["image"].shape[1] == -(-context["action"].shape[1] // 10)
    model.compute_loss(to_torch(batch, "cpu")).backward()
    assert model.obs_encoder.cameras["image"].stem[0].weight.grad.abs().sum() > 0


def test_the_paper_encoder_has_resnet_stem_and_the_cpu_one_keeps_its_own():
    assert get_method("bpp").preset("paper").obs.image_stem == "resnet"
    assert get_method("bpp").preset("cpu").obs.image_stem == "conv5"
    net = ResNetGN(32, widths=(16, 32), blocks=(1, 1), stem="resnet")
    seen = {}
    net.layers.register_forward_hook(lambda m, i, o: seen.update(shape=tuple(i[0].shape)))
    assert net(torch.zeros(2, 3, 224, 224, dtype=torch.uint8)).shape == (2, 32)
    assert seen["shape"] == (2, 16, 56, 56)  # a quarter of 224 after the 7x7 stride-2 convolution and the max-pool
    with pytest.raises(ValueError, match="image_stem"):
        ObsConfig(image_stem="vit")


def test_the_image_encoder_pools_over_the_whole_map_or_a_grid_of_regions():
    torch.manual_seed(0)
    images = torch.randint(0, 255, (3, 3, 32, 32), dtype=torch.uint8)
    whole, grid = ResNetGN(8, (8, 16), (1, 1)), ResNetGN(8, (8, 16), (1, 1), pool_grid=2)
    normed = (images.float() / 255 - whole.mean) / whole.std  # what the encoder does to its input first
    with torch.no_grad():
        x = whole.layers(whole.stem(normed))  # (3, 16, 8, 8)
        assert torch.allclose(whole(images), whole.proj(x.mean(dim=(2, 3))), atol=1e-6)  # the saved encoders' pool
        x = grid.layers(grid.stem(normed))
        # (3, 16, 4): each channel's mean in each quadrant, row by row
        quadrants = torch.stack([x[:, :, :4, :4], x[:, :, :4, 4:], x[:, :, 4:, :4], x[:, :, 4:, 4:]], dim=-1)
        quadrants = quadrants.mean(dim=(2, 3))
        assert grid.proj.in_features == 16 * 4
        assert torch.allclose(grid(images), grid.proj(quadrants.flatten(1)), atol=1e-6)
    with pytest.raises(ValueError, match="image_pool_grid"):
        ObsConfig(image_pool_grid=0)


@pytest.mark.slow
def test_image_encoder_trains_on_frames_of_any_batch_size_with_several_threads():
    """Frames arrive channels-last; PyTorch's multi-threaded CPU backward of a strided 1x1 convolution on such input
    corrupts memory at some batch sizes (the crash first seen on the GPU machine's 16 cores), so the residual blocks'
    shortcut must not be one. In a subprocess: the failure is a crash."""
    code = """
import os
import torch
from bpp.nn.vision import ResNetGN
torch.set_num_threads(min(4, len(os.sched_getaffinity(0))))
torch.manual_seed(0)
net = ResNetGN(16, (8, 16), (1, 1))
for n in (5, 11, 33, 5, 11, 33):
    frames = torch.randint(0, 255, (n, 32, 32, 3), dtype=torch.uint8).permute(0, 3, 1, 2)
    net.zero_grad()
    net(frames).square().sum().backward()
print("trained")
"""
    # Several threads, but no more than the cores: more threads than cores, beside the suite's other processes, made
    # torch's CPU backward run for many minutes on 2 cores.
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0 and "trained" in done.stdout, done.stderr[-2000:]
