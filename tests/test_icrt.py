from dataclasses import replace

import numpy as np
import pytest
import torch

from bpp.checkpoint import load_agent
from bpp.data.prompt_dataset import PromptBatchDataset
from bpp.errors import UserError
from bpp.policies.agent import PolicyAgent
from bpp.policies.icrt.model import PROMPT, ROLLOUT, ICRTModel
from bpp.policies.model import count_parameters
from bpp.policies.validation import PromptError
from bpp.train import TrainConfig, train
from bpp.utils import to_torch
from helpers import DRAW_FRAMES, config, obs_config, prompt_from_store, rollout

KEYS = ["board_pose", "cursor_on_board", "agent_pos", "pen_down"]
N = config("icrt").chunk_len


def _model(store, **overrides):
    torch.manual_seed(0)
    return ICRTModel(replace(config("icrt"), **overrides), store.stats).eval()


def _observe(episode: dict, t: int) -> dict:
    """Step t of a stored episode as an observation (its last step once t runs past the end)."""
    t = min(t, len(episode["action"]) - 1)
    return {k: episode[k][t] for k in KEYS}


def _act_open_loop(agent, episode: dict, steps: int) -> np.ndarray:
    """The agent's actions (steps, A) when it is shown a stored episode's observations, whatever it does."""
    return np.stack([agent.act(_observe(episode, t)) for t in range(steps)])


def _uncached_chunks(model, prompt: dict, episode: dict, actions: np.ndarray, start: int = 0) -> torch.Tensor:
    """The whole token sequence (prompt, then the rollout's observations every N steps from step `start` and the
    executed `actions`) in one pass without a cache: each rollout chunk's predicted raw actions (n, N, A)."""
    steps = len(actions)
    rollout = {
        "obs": {k: np.stack([_observe(episode, t)[k] for t in range(start, start + steps)])[None] for k in KEYS},
        "action": actions[None],
        "valid": np.ones((1, steps), dtype=bool),
    }
    prompt_tokens, prompt_valid = model.demo_tokens(to_torch(model.validate_context(prompt), "cpu"), PROMPT)
    rollout_tokens, rollout_valid = model.demo_tokens(to_torch(rollout, "cpu"), ROLLOUT)
    with torch.no_grad():
        out, _ = model.run(
            torch.cat([prompt_tokens, rollout_tokens], dim=1), torch.cat([prompt_valid, rollout_valid], dim=1)
        )
        chunks = model.head(out[0, prompt_tokens.shape[1] :: 2]).reshape(-1, N, model.action_dim)
    origin = model.chunk_origins(to_torch(rollout["obs"], "cpu"), N)
    return model.unnormalize_actions(chunks, None if origin is None else origin[0].reshape(-1, N, origin.shape[-1]))


def test_trains_saves_loads_and_draws(debug_store, tmp_path):
    cfg = TrainConfig(
        data=debug_store.path,
        out=tmp_path / "run",
        method="icrt",
        steps=3,
        batch_size=4,
        save_every=3,
        log_every=1,
        workers=0,
        warmup_steps=1,
    )
    ckpt = train(cfg, config("icrt"), progress=False)
    assert (ckpt / "ema.safetensors").is_file()
    agent = load_agent(tmp_path / "run")
    assert isinstance(agent.model, ICRTModel) and agent.n_action_steps == N
    result = rollout(agent, debug_store, 2, 0.2, seed=0, max_steps=35)
    assert 0 < result.steps <= 35 and result.attention is None
    again = rollout(agent, debug_store, 2, 0.2, seed=0, max_steps=35)
    assert again.steps == result.steps and again.best_chamfer == result.best_chamfer


@pytest.mark.parametrize("relative_to", ["", "agent_pos"], ids=["absolute", "relative"])
def test_cached_inference_equals_recomputing_the_whole_sequence(debug_store, relative_to):
    model = _model(debug_store, action_relative_to=relative_to)
    agent = PolicyAgent(model)
    prompt = prompt_from_store(debug_store, 0, KEYS)
    agent.reset(prompt)
    episode = debug_store.episode(1)
    acted = _act_open_loop(agent, episode, 6 * N)  # 6 inference calls, each extending the cache
    expected = _uncached_chunks(model, prompt, episode, acted)
    torch.testing.assert_close(torch.from_numpy(acted).reshape(6, N, -1), expected, rtol=1e-5, atol=1e-5)
    # Training's teacher-forced path (prompt cached once, whole rollout in one pass) predicts the same chunks.
    batch = to_torch({"obs": {k: episode[k][None, : 6 * N] for k in KEYS}, "action": acted[None]}, "cpu")
    batch["valid"] = torch.ones(1, 6 * N, dtype=torch.bool)
    with torch.no_grad():
        ctx = model.encode_context(to_torch(model.validate_context(prompt), "cpu"))
        chunks = model.rollout_chunks(ctx, batch)[0]
        origin = model.chunk_origins(batch["obs"], N)
        taught = model.unnormalize_actions(chunks, None if origin is None else origin[0].reshape(6, N, -1))
    torch.testing.assert_close(taught, expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("max_tokens", [128, 44])  # 44: both rollouts outgrow the context, at different steps
def test_padded_prompts_of_different_lengths_act_as_each_prompt_alone(debug_store, max_tokens):
    agent = PolicyAgent(_model(debug_store, max_tokens=max_tokens))
    prompts = [prompt_from_store(debug_store, e, KEYS) for e in (0, 7)]
    assert len(prompts[0]["action"]) != len(prompts[1]["action"])  # so the shorter one is padded
    episodes = [debug_store.episode(e) for e in (1, 8)]
    steps = 8 * N
    agent.reset_batch(prompts, seeds=[0, 1])
    together = np.stack(
        [agent.act_batch({k: np.stack([_observe(ep, t)[k] for ep in episodes]) for k in KEYS}) for t in range(steps)],
        axis=1,
    )
    for prompt, episode, batched in zip(prompts, episodes, together, strict=True):
        agent.reset(prompt)
        np.testing.assert_allclose(batched, _act_open_loop(agent, episode, steps), rtol=1e-5, atol=1e-5)


def test_long_rollouts_keep_the_prompt_and_the_latest_chunks(debug_store):
    max_tokens = 36
    model = _model(debug_store, max_tokens=max_tokens)
    agent = PolicyAgent(model)
    prompt = prompt_from_store(debug_store, 0, KEYS)  # 101 steps: 11 chunks, 22 tokens
    room = (max_tokens - 22) // 2  # 7 rollout chunks fit after it, the current one included
    agent.reset(prompt)
    episode = debug_store.episode(8)
    calls, acted = 16, []
    for t in range(calls * N):
        acted.append(agent.act(_observe(episode, t)))
        assert int(agent.context.lengths().max()) <= max_tokens
        assert agent.context.tokens.shape[1] <= max_tokens  # no slot is kept that no sample needs
    acted = np.stack(acted)
    assert np.isfinite(acted).all()
    # Past the limit, each chunk is what the prompt plus the latest chunks alone predict, from fresh positions.
    for call in range(room, calls):
        first = call - room + 1
        window = _uncached_chunks(model, prompt, episode, acted[first * N : (call + 1) * N], start=first * N)
        torch.testing.assert_close(torch.from_numpy(acted[call * N : (call + 1) * N]), window[-1], rtol=1e-5, atol=1e-5)
    # Training cuts rollouts that don't fit after the prompt and still learns from their first chunks.
    batch = to_torch(
        PromptBatchDataset(debug_store, model.data_spec(), frames=DRAW_FRAMES, batch_size=4, seed=3)[0], "cpu"
    )
    prompt_chunks = -(-batch["context"]["action"].shape[1] // N)
    assert batch["action"].shape[1] > (max_tokens // 2 - prompt_chunks) * N
    assert torch.isfinite(model.compute_loss(batch))


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        # The checks shared with BPP (validate_demo_context, tested in full in test_bpp.py) ...
        (lambda p: p.update(action=p["action"][:5]), "at least one chunk of 10 steps"),
        (lambda p: p["obs"].pop("agent_pos"), "lacks 'agent_pos'"),
        (lambda p: p["obs"]["board_pose"].__setitem__((3, 0), np.nan), "NaN"),
        # ... and the context limit: 128 tokens = 64 chunks, 4 of them kept for the rollout.
        (lambda p: p.update(action=np.zeros((610, 3), np.float32)), "at most 600 .*128 tokens"),
    ],
)
def test_bad_prompts_are_refused_with_a_reason(debug_store, mutate, message):
    prompt = prompt_from_store(debug_store, 0, KEYS)
    mutate(prompt)
    with pytest.raises(PromptError, match=message):
        PolicyAgent(_model(debug_store)).reset(prompt)


def test_loss_falls_when_overfitting_one_batch(debug_store):
    model = _model(debug_store).train()
    batch = to_torch(
        PromptBatchDataset(debug_store, model.data_spec(), frames=DRAW_FRAMES, batch_size=4, seed=0)[0], "cpu"
    )
    assert batch["valid"].shape == batch["action"].shape[:2] and not batch["valid"].all()  # padded demos
    optimizer = torch.optim.AdamW(model.parameters(), lr=3e-3)
    losses = []
    for step in range(30):
        loss = model.compute_loss(batch)
        optimizer.zero_grad()
        loss.backward()
        if step == 0:
            assert all(p.grad is not None for p in model.parameters())  # every module is used (DDP needs it)
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0], losses
    # ... and well below the best constant prediction (the median action): it uses its inputs.
    target = model.normalizer.normalize("action", batch["action"])[batch["valid"]]
    assert losses[-1] < 0.7 * (target - target.median(0).values).abs().mean().item(), losses


def test_preset_sizes(debug_store):
    sizes = {"debug": "canvas", "cpu": "canvas", "paper": "paper"}  # size preset -> observations
    counts = {
        name: count_parameters(ICRTModel(config("icrt", name, obs), debug_store.stats)) for name, obs in sizes.items()
    }
    print({name: f"{n / 1e6:.2f}M" for name, n in counts.items()})
    assert counts["debug"] < 1e5
    assert 2e6 < counts["cpu"] < 8e6
    assert 90e6 < counts["paper"] < 110e6  # 12 layers of D=768 (85M) + ResNet-18 (11M)


def test_image_observations_train_and_act(debug_store):
    obs = obs_config(image_keys=("image",), image_size=32, image_features=16, image_widths=(8, 16), image_blocks=(1, 1))
    model = _model(debug_store, obs=obs)
    batch = PromptBatchDataset(debug_store, model.data_spec(), frames=DRAW_FRAMES, batch_size=2, seed=0)[0]
    assert batch["obs"]["image"].shape[2:] == (32, 32, 3) and batch["context"]["obs"]["image"].shape[0] == 1
    model.compute_loss(to_torch(batch, "cpu")).backward()
    assert model.obs_encoder.cameras["image"].stem[0].weight.grad.abs().sum() > 0
    assert rollout(PolicyAgent(model), debug_store, 0, -0.4, seed=0, max_steps=25).steps == 25


def test_attention_readout_splits_the_observations_attention_between_prompt_chunks_and_rollout(debug_store):
    """With every key alike (no query-key weights), attention is even over the tokens a query may see: each prompt
    chunk's two tokens get 2 shares, the rollout so far its own count, a padded prompt's missing chunks none."""
    model = _model(debug_store)
    agent = PolicyAgent(model, record_attention=True)
    prompts = [prompt_from_store(debug_store, e, KEYS) for e in (0, 7)]
    chunks = [-(-len(p["action"]) // N) for p in prompts]
    assert chunks[0] != chunks[1]  # so the shorter prompt is padded
    episodes = [debug_store.episode(e) for e in (1, 8)]
    agent.reset_batch(prompts, seeds=[0, 1])
    for t in range(3 * N):
        agent.act_batch({k: np.stack([_observe(ep, t)[k] for ep in episodes]) for k in KEYS})
    real = np.stack(agent.attention_log)  # (calls, B, 1 + chunks)
    assert real.shape == (3, 2, 1 + max(chunks))
    np.testing.assert_allclose(real.sum(-1), 1.0, rtol=1e-5)
    short = int(np.argmin(chunks))
    assert (real[:, short, 1 + chunks[short] :] == 0).all()  # no attention on padding

    for block in model.transformer.blocks:
        with torch.no_grad():
            block.attn.qkv.weight[: 2 * block.attn.qkv.in_features] = 0  # queries and keys
            block.attn.qkv.bias[: 2 * block.attn.qkv.in_features] = 0
    agent.reset_batch(prompts, seeds=[0, 1])
    for t in range(3 * N):
        agent.act_batch({k: np.stack([_observe(ep, t)[k] for ep in episodes]) for k in KEYS})
    for call, maps in enumerate(agent.attention_log):
        rollout_tokens = 2 * call + 1  # the earlier chunks' observation and action tokens, and this observation
        for b, n in enumerate(chunks):
            seen = 2 * n + rollout_tokens
            expected = np.zeros(1 + max(chunks))
            expected[0], expected[1 : 1 + n] = rollout_tokens / seen, 2 / seen
            np.testing.assert_allclose(maps[b], expected, rtol=1e-5, atol=1e-7)


def test_a_limited_rollout_memory_acts_as_the_prompt_and_the_last_chunks_alone(debug_store):
    """With `limit_rollout_memory(k)` each chunk is what the prompt plus the rollout's last k chunks (its own
    included) predict from fresh positions, as past the context limit; 0 gives the whole rollout back."""
    model = _model(debug_store)
    agent = PolicyAgent(model)
    prompt = prompt_from_store(debug_store, 0, KEYS)
    episode = debug_store.episode(8)
    agent.reset(prompt)
    whole = _act_open_loop(agent, episode, 6 * N)
    model.limit_rollout_memory(2)
    agent.reset(prompt)
    acted = _act_open_loop(agent, episode, 6 * N)
    np.testing.assert_allclose(acted[: 2 * N], whole[: 2 * N], rtol=1e-5, atol=1e-5)  # nothing forgotten yet
    assert not np.allclose(acted[2 * N :], whole[2 * N :], atol=1e-4)
    for call in range(2, 6):
        first = call - 1
        window = _uncached_chunks(model, prompt, episode, acted[first * N : (call + 1) * N], start=first * N)
        torch.testing.assert_close(torch.from_numpy(acted[call * N : (call + 1) * N]), window[-1], rtol=1e-5, atol=1e-5)
    model.limit_rollout_memory(0)
    agent.reset(prompt)
    np.testing.assert_allclose(_act_open_loop(agent, episode, 6 * N), whole, rtol=1e-5, atol=1e-5)
    with pytest.raises(UserError, match="rollout memory"):
        model.limit_rollout_memory(-1)
