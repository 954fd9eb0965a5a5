"""The Goal-Image and Language baselines: train, checkpoint, act in the env, refuse bad contexts, learn."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from bpp.benchmarks.draw.dataset import DrawDataConfig, render_episode
from bpp.checkpoint import load_agent
from bpp.data.prompt_dataset import PromptBatchDataset
from bpp.drawing.procedural import describe_parts
from bpp.errors import UserError
from bpp.nn.text import pretrained_text_dir
from bpp.policies.agent import PolicyAgent
from bpp.policies.goal_image.model import GoalImageModel
from bpp.policies.language.model import LanguageModel
from bpp.policies.registry import get_method
from bpp.policies.validation import ContextError
from bpp.train import TrainConfig, train
from bpp.utils import from_dict, to_dict, to_torch
from helpers import DRAW_FRAMES, config, context_for, obs_config, rollout, rollout_batch

METHODS = ["goal_image", "language"]


@pytest.fixture
def store_for(debug_store, described_store):
    """The store a method trains on: Language needs instructions, Goal-Image any DrawAnything store."""
    return lambda method: described_store if method == "language" else debug_store


def _model(method: str, store, cfg=None):
    torch.manual_seed(0)
    m = get_method(method)
    return m.model_cls(cfg or config(m.name), store.stats)


def test_registered_with_presets_that_round_trip_through_json():
    for method in METHODS:
        m = get_method(method)
        assert {"debug", "cpu", "paper"} <= set(m.presets)
        for cfg in m.presets.values():
            assert from_dict(m.config_cls, to_dict(cfg)) == cfg
    assert (
        config("goal_image", "paper", "paper").shares_camera_encoder
        and not config("goal_image", "cpu").shares_camera_encoder
    )


def test_describe_gives_each_task_its_parts_in_words(debug_store, described_store):
    assert describe_parts(["line", "move", "oval"]) == "draw a line, then lift the pen and move, then draw an oval"
    for task in described_store.tasks:
        assert task["instruction"] == describe_parts(task["info"]["parts"])
    assert all(task["instruction"] == "" for task in debug_store.tasks)  # off by default
    # Describing changes no drawing: the first tasks of both stores (same seed) are the same drawings.
    for t in range(described_store.num_tasks):
        np.testing.assert_array_equal(described_store.task_array("strokes", t), debug_store.task_array("strokes", t))
    with pytest.raises(ValueError, match="describe needs procedural"):
        DrawDataConfig(source="human", describe=True)


@pytest.mark.parametrize("method", METHODS)
def test_trains_saves_loads_and_acts_in_the_env(method, store_for, tmp_path):
    store = store_for(method)
    cfg = TrainConfig(
        data=store.path,
        out=tmp_path / "run",
        method=method,
        steps=3,
        batch_size=8,
        save_every=3,
        log_every=1,
        workers=0,
        warmup_steps=1,
    )
    train(cfg, config(method), progress=False)
    agent = load_agent(tmp_path / "run")
    assert agent.model.method == method
    result = rollout(agent, store, 1, 0.3, seed=0, max_steps=20)
    assert 0 < result.steps <= 20 and 0 < result.best_chamfer <= result.final_chamfer
    again = rollout(agent, store, 1, 0.3, seed=0, max_steps=20)
    assert (again.steps, again.best_chamfer) == (result.steps, result.best_chamfer)


def test_language_text_encoder_choices_are_checked():
    with pytest.raises(UserError, match="needs its own tokenizer"):
        replace(config("language"), text_encoder="pretrained", tokenizer="bytes")
    with pytest.raises(UserError, match="pins a pretrained text encoder's weights"):
        replace(config("language"), pretrained_text_sha256={"model.safetensors": "0" * 64})
    with pytest.raises(UserError, match="not a pretrained text encoder"):
        pretrained_text_dir("/nonexistent/model")


@pytest.mark.parametrize("method", METHODS)
def test_batched_rollouts_match_single_rollouts(method, store_for):
    store = store_for(method)
    agent = PolicyAgent(_model(method, store).eval())
    episodes, angles, seeds = [0, 5], [0.3, -0.5], [11, 12]
    together = rollout_batch(agent, store, episodes, angles, seeds, max_steps=14)
    for ep, angle, seed, batched in zip(episodes, angles, seeds, together, strict=True):
        alone = rollout(agent, store, ep, angle, seed=seed, max_steps=14)
        assert alone.steps == batched.steps
        assert alone.best_chamfer == pytest.approx(batched.best_chamfer, abs=1e-6)


@pytest.mark.parametrize("method", METHODS)
def test_overfitting_one_batch_lowers_the_loss(method, store_for):
    store = store_for(method)
    model = _model(method, store)
    batch = to_torch(PromptBatchDataset(store, model.data_spec(), frames=DRAW_FRAMES, batch_size=16, seed=0)[0], "cpu")
    optimizer = torch.optim.Adam(model.parameters(), lr=2e-3)

    def loss():  # the same noise and diffusion steps every time: a fixed regression problem
        return model(batch, torch.Generator().manual_seed(0))

    first = loss()
    first.backward()
    assert all(p.grad is not None for p in model.parameters())  # every module is used (DDP needs it)
    for _ in range(30):
        optimizer.zero_grad()
        loss().backward()
        optimizer.step()
    assert loss().item() < 0.25 * first.item()


GOOD_GOAL = np.zeros((32, 32, 3), np.uint8)


@pytest.mark.parametrize(
    ("context", "message"),
    [
        ({"goal": GOOD_GOAL}, r"must be a dict \{'image': \(32, 32, 3\) uint8"),
        (GOOD_GOAL, "must be a dict"),
        ({"image": GOOD_GOAL.astype(np.float32)}, "must be uint8 RGB"),
        ({"image": np.zeros((64, 64, 3), np.uint8)}, r"shape \(32, 32, 3\) as in training, got \(64, 64, 3\)"),
        ({"image": GOOD_GOAL[..., :1]}, r"got \(32, 32, 1\)"),
        ({"image": GOOD_GOAL[None]}, r"got \(1, 32, 32, 3\)"),
    ],
)
def test_goal_image_refuses_bad_goals(debug_store, context, message):
    agent = PolicyAgent(_model("goal_image", debug_store))
    agent.reset(context_for(agent.model, debug_store, 0))  # the real goal is fine
    assert agent.context.shape == (1, 16)
    with pytest.raises(ContextError, match=message):
        agent.reset(context)


@pytest.mark.parametrize(
    ("context", "message"),
    [
        ({"instruction": "draw a line"}, r"must be a dict \{'text': str\}"),
        ({"text": ["draw a line"]}, "must be a str, got list"),
        ({"text": ""}, "this task has no instruction; Language is not offered for it"),
        ({"text": "  \n"}, "this task has no instruction"),
        ({"text": "x" * 300}, "302 tokens .* accepts 256"),
    ],
)
def test_language_refuses_bad_instructions(described_store, context, message):
    agent = PolicyAgent(_model("language", described_store))
    agent.reset(context_for(agent.model, described_store, 0))
    with pytest.raises(ContextError, match=message):
        agent.reset(context)


def test_language_is_not_offered_for_tasks_without_instructions(debug_store):
    model = _model("language", debug_store)
    with pytest.raises(ContextError, match="Language is not offered"):
        PolicyAgent(model).reset(context_for(model, debug_store, 0))
    with pytest.raises(ValueError, match="carry no instructions"):
        PromptBatchDataset(debug_store, model.data_spec(), frames=DRAW_FRAMES)


def test_instruction_encoding_ignores_padding(described_store):
    model = LanguageModel(config("language"), described_store.stats).eval()
    texts = ["draw a line", "draw a curve, then lift the pen and move, then draw an oval"]
    both = model.encode_context({"text": texts})
    assert both.shape == (2, config("language").text.dim)
    for i, text in enumerate(texts):
        torch.testing.assert_close(both[i : i + 1], model.encode_context({"text": [text]}), rtol=1e-5, atol=1e-5)
    assert not torch.allclose(both[0], both[1])


@pytest.mark.parametrize("observes_images", [False, True])
def test_goal_images_are_the_prompts_final_frames(debug_store, observes_images):
    cfg = config("goal_image")
    if observes_images:
        obs = obs_config(image_keys=("image",), image_size=32, image_widths=(8, 16), image_blocks=(1, 1))
        cfg = replace(cfg, obs=obs)
    spec = GoalImageModel(cfg, debug_store.stats).data_spec()
    data = PromptBatchDataset(
        debug_store, spec, frames=DRAW_FRAMES, batch_size=4, seed=0, goal_cache_bytes=1
    )  # room for 1 frame
    for episode in (3, 20, 3):
        if observes_images:
            data._episode_frames(episode, "image", 32)  # as training windows would: the goal comes from these
        goal = data.context(episode)["image"]
        np.testing.assert_array_equal(goal, render_episode(debug_store, episode, spec.context_image_size)[-1:])
    assert len(data._goal_cache) == (0 if observes_images else 1)


def test_goal_image_with_image_observations_shares_the_camera_encoder(debug_store):
    obs = obs_config(image_keys=("image",), image_size=32, image_features=16, image_widths=(8, 16), image_blocks=(1, 1))
    cfg = replace(config("goal_image"), obs=obs)
    model = GoalImageModel(cfg, debug_store.stats)
    camera = model.obs_encoder.cameras["image"]
    assert model.goal_network() is camera
    assert not any(k.startswith("goal_encoder") for k in model.state_dict())  # the weights are stored once
    own = GoalImageModel(config("goal_image"), debug_store.stats)  # state-only: a goal encoder of its own
    assert any(k.startswith("goal_encoder") for k in own.state_dict())
    batch = PromptBatchDataset(debug_store, model.data_spec(), frames=DRAW_FRAMES, batch_size=4, seed=0)[0]
    assert batch["obs"]["image"].shape == (4, 2, 32, 32, 3) and batch["context"]["image"].shape == (1, 32, 32, 3)
    model.encode_context(to_torch(batch["context"], "cpu")).sum().backward()
    assert camera.stem[0].weight.grad.abs().sum() > 0  # the goal image trains the camera encoder
    with pytest.raises(ValueError, match="must equal obs.image_size"):
        replace(cfg, goal_image_size=64)
    with pytest.raises(ValueError, match="not among the observed cameras"):
        replace(cfg, goal_camera="wrist")
    assert rollout(PolicyAgent(model), debug_store, 0, -0.4, seed=0, max_steps=13).steps == 13
