import json
import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from bpp.checkpoint import load_agent, prune_checkpoints, resolve_checkpoint
from bpp.data.prompt_dataset import DataSpec, PromptBatchDataset
from bpp.policies.agent import PolicyAgent
from bpp.policies.bpp.config import PromptConfig
from bpp.policies.bpp.model import BPPModel, PromptError
from bpp.policies.model import count_parameters
from bpp.train import TrainConfig, train
from bpp.utils import to_torch
from helpers import DRAW_FRAMES, config, obs_config, prompt_from_store, rollout

KEYS = ["board_pose", "cursor_on_board", "agent_pos", "pen_down"]


def _dataset(store, **kw):
    return PromptBatchDataset(store, DataSpec(lowdim_keys=tuple(KEYS), **kw), frames=DRAW_FRAMES, batch_size=8, seed=0)


def _model(store, cfg=None):
    torch.manual_seed(0)
    return BPPModel(cfg or config("bpp"), store.stats)


def test_batches_are_deterministic_and_from_one_task(debug_store):
    ds = _dataset(debug_store)
    a, b = ds[5], ds[5]
    for key in KEYS:
        np.testing.assert_array_equal(a["obs"][key], b["obs"][key])
    assert a["obs"]["agent_pos"].shape == (8, 2, 2) and a["action"].shape == (8, 16, 3)
    assert a["context"]["action"].shape[0] == 1 and a["context"]["valid"].all()
    # The prompt is a demonstration of the batch's task and no window comes from it.
    task_of = debug_store.column("task_index")
    prompt_len = a["context"]["action"].shape[1]
    prompt_eps = [
        e
        for e in debug_store.task_episodes()[int(a["task"][0])]
        if debug_store.episode_slice(e).stop - debug_store.episode_slice(e).start == prompt_len
    ]
    assert prompt_eps and all(task_of[e] == a["task"] for e in prompt_eps)
    other = ds[6]
    assert not np.array_equal(a["action"], other["action"])


def test_window_padding_repeats_edges(debug_store):
    ds = _dataset(debug_store)
    batch = ds[0]
    # Action chunks are a window of one episode: consecutive targets never jump across the canvas.
    jumps = np.abs(np.diff(batch["action"][..., :2], axis=1)).max()
    assert jumps < 200


def test_loss_and_shapes(debug_store):
    model = _model(debug_store)
    batch = to_torch(_dataset(debug_store)[0], "cpu")
    loss = model.compute_loss(batch)
    assert loss.ndim == 0 and torch.isfinite(loss)
    loss.backward()
    ctx = model.encode_prompt(batch["context"])
    out = model.predict_action(batch["obs"], ctx, return_attention=True)
    assert out["action"].shape == (8, 16, 3)
    assert out["attention"].shape == (8, ctx.num_chunks + 1)
    torch.testing.assert_close(out["attention"].sum(-1), torch.ones(8))


def test_cached_prompt_gives_the_same_actions_as_recomputing_it(debug_store):
    model = _model(debug_store).eval()
    batch = to_torch(_dataset(debug_store)[3], "cpu")
    noise = torch.randn(8, 16, 3, generator=torch.Generator().manual_seed(0))
    cached = model.encode_prompt(batch["context"])
    a = model.predict_action(batch["obs"], cached, noise=noise)["action"]
    b = model.predict_action(batch["obs"], cached, noise=noise)["action"]
    c = model.predict_action(batch["obs"], model.encode_prompt(batch["context"]), noise=noise)["action"]
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    torch.testing.assert_close(a, c, rtol=0, atol=0)


def test_prompt_encoded_once_per_rollout_and_prompt_encoder_once_per_call(debug_store):
    model = _model(debug_store)
    calls = {"encode": 0, "prompt_encoder": 0, "unet": 0}
    original = model.encode_prompt

    def counting_encode(prompt):
        calls["encode"] += 1
        return original(prompt)

    model.encode_prompt = counting_encode
    model.prompt_encoder.register_forward_hook(
        lambda *a: calls.__setitem__("prompt_encoder", calls["prompt_encoder"] + 1)
    )
    model.head.net.register_forward_hook(lambda *a: calls.__setitem__("unet", calls["unet"] + 1))
    agent = PolicyAgent(model)
    prompt = prompt_from_store(debug_store, 0, KEYS)
    agent.reset(prompt, seed=0)
    assert calls["encode"] == 1
    ep = debug_store.episode(1)
    for t in range(24):
        agent.act({k: ep[k][t] for k in KEYS})
    ta, k = model.cfg.horizons.n_action_steps, model.cfg.diffusion.num_inference_steps
    assert calls["encode"] == 1  # never again during the rollout
    assert calls["prompt_encoder"] == 24 // ta  # once per inference call ...
    assert calls["unet"] == k * (24 // ta)  # ... then every denoising step without the prompt


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda p: p.update(action=p["action"][:0]), "at least one chunk"),
        (lambda p: p.update(action=p["action"][:5]), "at least one chunk"),
        (lambda p: p["obs"].pop("agent_pos"), "lacks 'agent_pos'"),
        (lambda p: p["obs"].update(agent_pos=p["obs"]["agent_pos"][:, :1]), r"must have shape \(steps, 2\)"),
        (lambda p: p["obs"]["board_pose"].__setitem__((3, 0), np.nan), "NaN"),
        (lambda p: p["action"].__setitem__((2, 1), np.inf), "NaN"),
        (lambda p: p.update(action=np.zeros((len(p["action"]), 7), np.float32)), r"shape \(steps, 3\)"),
        (lambda p: p["obs"].update(pen_down=p["obs"]["pen_down"][:-1]), "steps, actions have"),
        (lambda p: p.update(action=np.zeros((900, 3), np.float32)), "at most 800"),
        (lambda p: p.pop("obs"), "must be a dict"),
    ],
)
def test_bad_prompts_are_refused_with_a_reason(debug_store, mutate, message):
    agent = PolicyAgent(_model(debug_store))
    prompt = prompt_from_store(debug_store, 0, KEYS)
    prompt["obs"] = {k: v.copy() for k, v in prompt["obs"].items()}
    prompt["action"] = prompt["action"].copy()
    mutate(prompt)
    with pytest.raises(PromptError, match=message):
        agent.reset(prompt)


@pytest.mark.parametrize(
    "prompt_cfg",
    [
        PromptConfig(pooling="none", num_sinks=1),
        PromptConfig(pooling="obs"),
        PromptConfig(use_obs=False, use_proprio=False),
        PromptConfig(use_action=False, chunk_len=5),
    ],
)
def test_prompt_ablations_train_and_act(debug_store, prompt_cfg):
    cfg = replace(config("bpp"), prompt=prompt_cfg)
    model = _model(debug_store, cfg)
    batch = to_torch(_dataset(debug_store)[0], "cpu")
    model.compute_loss(batch).backward()
    assert all(p.grad is not None for p in model.parameters())  # every module is used (DDP needs it)
    ctx = model.encode_prompt(batch["context"])
    assert model.predict_action(batch["obs"], ctx)["action"].shape == (8, 16, 3)


def test_rollout_memory_windows_hold_the_episode_earlier(debug_store):
    """A window with a rollout memory holds the same episode's states Δt and 2Δt steps before its current one
    (the first one's before the episode starts), then the usual To-step history: the same draws as a 21-step one."""
    memory = _dataset(debug_store, memory_offsets=(-20, -10))[4]["obs"]
    long = _dataset(debug_store, n_obs_steps=21, horizon=22)[4]["obs"]
    plain = _dataset(debug_store)[4]["obs"]
    for key in KEYS:
        assert memory[key].shape[1] == 4
        np.testing.assert_array_equal(memory[key], long[key][:, [0, 10, 19, 20]])
        np.testing.assert_array_equal(memory[key][:, 2:], plain[key])
    assert not np.array_equal(memory["agent_pos"][:, 0], memory["agent_pos"][:, 3])  # some windows moved


def test_rollout_memory_is_read_from_the_rollout_at_chunk_boundaries(debug_store):
    model = _model(debug_store, replace(config("bpp"), prompt=PromptConfig(rollout_memory=2, chunk_len=10)))
    assert model.data_spec().obs_offsets == (-20, -10, -1, 0)
    seen = []
    predict = model.predict_action
    model.predict_action = lambda obs, *a, **kw: seen.append(obs["agent_pos"][0].numpy()) or predict(obs, *a, **kw)
    agent = PolicyAgent(model, n_action_steps=1)
    agent.reset(prompt_from_store(debug_store, 0, KEYS), seed=0)
    ep = debug_store.episode(1)
    for t in range(25):
        agent.act({k: ep[k][t] for k in KEYS})
    for t in (0, 5, 12, 24):
        np.testing.assert_array_equal(seen[t], ep["agent_pos"][[max(t - 20, 0), max(t - 10, 0), max(t - 1, 0), t]])


def test_rollout_memory_trains_and_changes_the_actions(debug_store):
    cfg = replace(config("bpp"), prompt=PromptConfig(rollout_memory=2))
    model = _model(debug_store, cfg)
    ds = PromptBatchDataset(debug_store, model.data_spec(), frames=DRAW_FRAMES, batch_size=8, seed=0)
    batch = to_torch(ds[0], "cpu")
    model.compute_loss(batch).backward()
    assert all(p.grad is not None for p in model.parameters())  # the memory's embeddings included
    ctx = model.encode_prompt(batch["context"])
    noise = torch.randn(8, 16, 3, generator=torch.Generator().manual_seed(0))
    a = model.predict_action(batch["obs"], ctx, noise=noise, return_attention=True)
    moved = {k: v.clone() for k, v in batch["obs"].items()}
    moved["agent_pos"][:, 0] += 50.0  # an earlier state, the current ones unchanged
    b = model.predict_action(moved, ctx, noise=noise)
    assert a["attention"].shape == (8, ctx.num_chunks + 1)
    assert not torch.allclose(a["action"], b["action"])


def test_paper_preset_size():
    stats = {k: {"min": [0.0] * n, "max": [1.0] * n} for k, n in [("agent_pos", 2), ("pen_down", 1), ("action", 3)]}
    model = BPPModel(config("bpp", "paper", "paper"), stats)
    prompt_encoder = count_parameters(model.prompt_encoder)
    unet = count_parameters(model.head)
    print(f"paper preset: prompt encoder {prompt_encoder / 1e6:.1f}M, action decoder {unet / 1e6:.1f}M")
    assert 0.9 * 57e6 < prompt_encoder < 1.1 * 57e6
    assert 0.9 * 151e6 < unet < 1.1 * 151e6


def _train(store, out, steps, save_every, resume=False, keep_checkpoints=3):
    cfg = TrainConfig(
        data=store.path,
        out=out,
        steps=steps,
        batch_size=8,
        save_every=save_every,
        keep_checkpoints=keep_checkpoints,
        log_every=2,
        workers=0,
        warmup_steps=2,
        resume=resume,
    )
    return train(cfg, config("bpp"), progress=False)


def test_resume_reproduces_an_uninterrupted_run(debug_store, tmp_path):
    full = _train(debug_store, tmp_path / "full", steps=6, save_every=3)
    # "Kill" a run after step 3: keep only its first checkpoint, then resume it to step 6.
    part = tmp_path / "part"
    shutil.copytree(tmp_path / "full", part)
    shutil.rmtree(part / "checkpoints" / "step_00000006")
    (part / "checkpoints" / "last").write_text("step_00000003")
    resumed = _train(debug_store, part, steps=6, save_every=3, resume=True)
    for name in ("model.safetensors", "ema.safetensors", "optimizer.safetensors"):
        a, b = load_file(full / name), load_file(resumed / name)
        assert a.keys() == b.keys()
        for k in a:
            torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)
    with pytest.raises(FileExistsError, match="--resume"):
        _train(debug_store, part, steps=6, save_every=3)


def test_runs_fuse_the_optimiser_and_an_unfused_run_resumes_unfused(debug_store, tmp_path):
    run = tmp_path / "run"
    _train(debug_store, run, steps=6, save_every=3)
    shutil.rmtree(run / "checkpoints" / "step_00000006")  # killed after step 3
    (run / "checkpoints" / "last").write_text("step_00000003")
    saved = run / "checkpoints" / "step_00000003" / "state.json"
    state = json.loads(saved.read_text())
    assert [g["fused"] for g in state["optimizer"]["param_groups"]] == [True]  # on a CPU too
    state["optimizer"]["param_groups"][0]["fused"] = None  # as a run checkpointed before that
    saved.write_text(json.dumps(state))
    _train(debug_store, run, steps=6, save_every=3, resume=True)
    resumed = json.loads((run / "checkpoints" / "step_00000006" / "state.json").read_text())
    assert [g["fused"] for g in resumed["optimizer"]["param_groups"]] == [None]  # continues as it began


def test_only_the_newest_checkpoints_stay_on_disk(debug_store, tmp_path):
    ckpt = _train(debug_store, tmp_path / "run", steps=5, save_every=1, keep_checkpoints=2)
    folders = sorted(p.name for p in (tmp_path / "run" / "checkpoints").iterdir() if p.is_dir())
    assert folders == ["step_00000004", "step_00000005"]
    assert ckpt.name == "step_00000005"
    everything = _train(debug_store, tmp_path / "all", steps=3, save_every=1, keep_checkpoints=0)
    assert len([p for p in everything.parent.iterdir() if p.is_dir()]) == 3
    # `last` may name an older folder (a run rolled back by hand): that one is never deleted.
    (tmp_path / "run" / "checkpoints" / "last").write_text("step_00000004")
    assert prune_checkpoints(tmp_path / "run" / "checkpoints", keep=1) == [tmp_path / "run/checkpoints/step_00000005"]
    assert resolve_checkpoint(tmp_path / "run").name == "step_00000004"


def test_checkpoint_round_trip_acts_in_the_env(debug_store, tmp_path):
    ckpt = _train(debug_store, tmp_path / "run", steps=4, save_every=4)
    assert {p.name for p in ckpt.iterdir()} >= {"model.safetensors", "ema.safetensors", "state.json"}
    agent = load_agent(tmp_path / "run", record_attention=True)
    result = rollout(agent, debug_store, 2, 0.2, seed=0, max_steps=30)
    assert result.steps <= 30 and 0 < result.best_chamfer <= result.final_chamfer
    assert len(result.attention) == -(-result.steps // agent.n_action_steps)
    # Same seed, same rollout.
    again = rollout(agent, debug_store, 2, 0.2, seed=0, max_steps=30)
    assert again.best_chamfer == result.best_chamfer and again.steps == result.steps


@pytest.mark.slow
def test_ddp_two_processes_on_cpu(debug_store, tmp_path):
    out = tmp_path / "ddp"
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc-per-node",
        "2",
        "--master-port",
        "29531",
        "-m",
        "bpp.cli",
        "train",
        "--data",
        str(debug_store.path),
        "--out",
        str(out),
        "--preset",
        "debug",
        "--steps",
        "4",
        "--batch-size",
        "4",
        "--workers",
        "0",
        "--warmup-steps",
        "1",
        "--save-every",
        "4",
    ]
    done = subprocess.run(
        cmd,
        capture_output=True,
        text=True,
        timeout=300,
        env={
            "OMP_NUM_THREADS": "1",
            "PATH": "/usr/bin:/bin",
            "HOME": str(Path.home()),
            **{k: os.environ[k] for k in ("PYTHONPATH",) if k in os.environ},  # bpp run from a source tree
        },
    )
    assert done.returncode == 0, done.stderr[-3000:]
    state = (out / "checkpoints" / "step_00000004" / "state.json").read_text()
    assert '"world_size": 2' in state


@pytest.mark.slow
def test_rollout_command_writes_pictures(debug_store, tmp_path):
    _train(debug_store, tmp_path / "run", steps=2, save_every=2)
    out = tmp_path / "rollout"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "bpp.cli",
            "draw",
            "rollout",
            str(tmp_path / "run"),
            "--store",
            str(debug_store.path),
            "--episode",
            "4",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "best Chamfer" in done.stdout
    assert (out / "rollout.png").stat().st_size > 5_000 and (out / "rollout.gif").stat().st_size > 5_000


def test_image_observations_train_and_act(debug_store):

    obs = obs_config(image_keys=("image",), image_size=32, image_features=16, image_widths=(8, 16), image_blocks=(1, 1))
    cfg = replace(config("bpp"), obs=obs)
    model = _model(debug_store, cfg)
    ds = _dataset(debug_store, image_keys=("image",), image_size=32)
    batch = ds[0]
    assert batch["obs"]["image"].shape == (8, 2, 32, 32, 3) and batch["obs"]["image"].dtype == np.uint8
    assert batch["context"]["obs"]["image"].shape[2:] == (32, 32, 3)
    model.compute_loss(to_torch(batch, "cpu")).backward()
    assert model.obs_encoder.cameras["image"].stem[0].weight.grad.abs().sum() > 0
    result = rollout(PolicyAgent(model), debug_store, 0, -0.4, seed=0, max_steps=13)
    assert result.steps == 13


def test_rendered_frames_are_cached_within_a_byte_budget(debug_store):
    from bpp.benchmarks.draw.dataset import render_episode

    frames = {e: render_episode(debug_store, e, 16) for e in (0, 1, 2)}
    budget = frames[0].nbytes + max(frames[1].nbytes, frames[2].nbytes)  # room for two of the three episodes
    ds = PromptBatchDataset(
        debug_store,
        DataSpec(lowdim_keys=tuple(KEYS), image_keys=("image",), image_size=16),
        frames=DRAW_FRAMES,
        batch_size=8,
        seed=0,
        frame_cache_bytes=budget,
    )
    for e in (0, 1, 0, 2):  # 0 used last before 2 arrives: 1 is the one evicted
        np.testing.assert_array_equal(ds._episode_frames(e, "image", 16), frames[e])
    assert [k[0] for k in ds._frame_cache] == [0, 2] and ds._frame_cache.nbytes == frames[0].nbytes + frames[2].nbytes


def test_padded_prompts_of_different_lengths_match_unpadded(debug_store):
    """Prompts of different lengths batched with padding + masks act exactly like each prompt alone."""
    model = _model(debug_store).eval()
    ds = _dataset(debug_store)
    p1, p2 = ds.context(0), ds.context(7)
    l1, l2 = p1["action"].shape[1], p2["action"].shape[1]
    assert l1 != l2
    length = max(l1, l2)

    def pad(p):
        n = length - p["action"].shape[1]
        return {
            "obs": {k: np.pad(v, ((0, 0), (0, n), (0, 0)), mode="edge") for k, v in p["obs"].items()},
            "action": np.pad(p["action"], ((0, 0), (0, n), (0, 0)), mode="edge"),
            "valid": np.pad(p["valid"], ((0, 0), (0, n))),
        }

    both = {
        "obs": {k: np.concatenate([pad(p1)["obs"][k], pad(p2)["obs"][k]]) for k in KEYS},
        "action": np.concatenate([pad(p1)["action"], pad(p2)["action"]]),
        "valid": np.concatenate([pad(p1)["valid"], pad(p2)["valid"]]),
    }
    obs = to_torch({k: v[:2] for k, v in ds[0]["obs"].items()}, "cpu")
    noise = torch.randn(2, 16, 3, generator=torch.Generator().manual_seed(1))
    batched = model.predict_action(obs, model.encode_prompt(to_torch(both, "cpu")), noise=noise)["action"]
    for i, p in enumerate((p1, p2)):
        alone = model.predict_action(
            {k: v[i : i + 1] for k, v in obs.items()}, model.encode_prompt(to_torch(p, "cpu")), noise=noise[i : i + 1]
        )["action"]
        torch.testing.assert_close(batched[i : i + 1], alone, rtol=1e-5, atol=1e-4)


def test_batched_rollouts_match_single_rollouts(debug_store):
    """Rollouts stepped together in one batch give exactly what each gives alone (per-rollout noise seeds)."""
    from helpers import rollout_batch

    agent = PolicyAgent(_model(debug_store).eval())
    episodes, angles, seeds = [0, 4, 9], [0.3, -0.5, 0.1], [11, 12, 13]
    together = rollout_batch(agent, debug_store, episodes, angles, seeds, max_steps=30)
    for ep, angle, seed, batched in zip(episodes, angles, seeds, together, strict=True):
        alone = rollout(agent, debug_store, ep, angle, seed=seed, max_steps=30)
        assert alone.steps == batched.steps
        assert alone.best_chamfer == pytest.approx(batched.best_chamfer, abs=1e-6)


def test_fourier_embeddings_train_and_act(debug_store):
    """The state-only presets' nonlinear input embeddings: every module gets a gradient and the model acts."""

    cfg = replace(
        config("bpp"),
        obs=obs_config(lowdim_fourier_octaves=3, lowdim_features=16),
        prompt=PromptConfig(num_sinks=2, action_fourier_octaves=3),
    )
    model = _model(debug_store, cfg)
    assert model.obs_encoder.dims[-4:] == [16, 16, 16, 16]
    batch = to_torch(_dataset(debug_store)[0], "cpu")
    model.compute_loss(batch).backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())
    ctx = model.encode_prompt(batch["context"])
    assert torch.isfinite(model.predict_action(batch["obs"], ctx)["action"]).all()


def test_fourier_features_make_nearby_inputs_similar():
    """Why the embedding exists: with Fourier features, the dot product peaks at the nearest input, not the
    furthest along the query's direction (which is what a linear embedding's dot product rewards)."""
    from bpp.nn.lowdim import FourierFeatures

    ff = FourierFeatures(5)
    keys = torch.linspace(-1, 1, 41)[:, None]
    for q in (-0.6, 0.1, 0.45):
        query = torch.tensor([[q]])
        scores = ff(keys)[:, 1:] @ ff(query)[0, 1:]  # the sin/cos part
        assert abs(keys[scores.argmax(), 0].item() - q) <= 0.05
        assert abs(keys[(keys @ query[0]).argmax(), 0].item()) == 1.0  # linear: an end of the range wins
