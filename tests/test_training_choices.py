"""Training choices for small budgets: several tasks per batch, actions relative to the robot's state, and what the
diffusion decoder predicts."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from bpp.checkpoint import load_agent
from bpp.data.prompt_dataset import PromptBatchDataset, index_contexts
from bpp.evaluation.protocol import Protocol
from bpp.policies.agent import PolicyAgent
from bpp.policies.bpp.model import BPPModel
from bpp.policies.config import DEBUG_DIFFUSION, PREDICTION_TYPES
from bpp.policies.diffusion import DiffusionHead
from bpp.policies.icrt.model import ICRTModel
from bpp.policies.registry import get_method
from bpp.train import TrainConfig, train
from bpp.utils import to_torch
from helpers import DRAW_FRAMES, config

RELATIVE = {"bpp": "agent_pos", "goal_image": "agent_pos", "icrt": "agent_pos"}


def _model(store, method: str, **overrides):
    torch.manual_seed(0)
    m = get_method(method)
    return m.model_cls(replace(config(m.name), **overrides), store.stats)


def test_grouped_batches_take_each_sample_from_its_own_tasks_other_demos(debug_store):
    model = _model(debug_store, "bpp")
    ds = PromptBatchDataset(
        debug_store, model.data_spec(), frames=DRAW_FRAMES, batch_size=12, seed=0, tasks_per_batch=4
    )
    batch = ds[7]
    assert batch["task"].shape == (4,) and len(set(batch["task"].tolist())) == 4  # distinct tasks
    np.testing.assert_array_equal(batch["context_index"], np.repeat(np.arange(4), 3))
    ctx = batch["context"]
    assert ctx["action"].shape[0] == 4 and ctx["valid"].shape[0] == 4
    lengths = ctx["valid"].sum(1)
    assert lengths.max() == ctx["valid"].shape[1] and not ctx["valid"].all()  # padded to the longest prompt
    task_of = debug_store.column("task_index")
    for g, task in enumerate(batch["task"]):
        # The context is a demonstration of the group's task ...
        prompt_eps = [
            e for e in debug_store.task_episodes()[task] if debug_store.episode(e)["action"].shape[0] == lengths[g]
        ]
        assert prompt_eps
        first = ctx["action"][g, 0]
        prompt_ep = [e for e in prompt_eps if np.array_equal(debug_store.episode(e)["action"][0], first)]
        assert len(prompt_ep) == 1 and task_of[prompt_ep[0]] == task
        # ... and the group's windows come from the task's other demonstrations.
        for i in np.flatnonzero(batch["context_index"] == g):
            window = batch["action"][i]
            sources = [
                e
                for e in debug_store.task_episodes()[task]
                if any(np.array_equal(window[-1], a) for a in debug_store.episode(e)["action"])
            ]
            assert sources and prompt_ep[0] not in sources
    assert ds[7]["context"]["action"].tobytes() == ctx["action"].tobytes()  # deterministic


def test_batch_size_must_split_into_tasks(debug_store):
    model = _model(debug_store, "bpp")
    with pytest.raises(ValueError, match="multiple of tasks_per_batch"):
        PromptBatchDataset(debug_store, model.data_spec(), frames=DRAW_FRAMES, batch_size=10, tasks_per_batch=4)


@pytest.mark.parametrize("method", ["bpp", "goal_image", "icrt"])
def test_grouped_loss_equals_the_loss_with_one_context_per_sample(debug_store, method):
    """Encoding G contexts once and selecting per sample is exactly the same as giving each sample its own copy."""
    model = _model(debug_store, method).eval()
    spec = model.data_spec()
    batch = to_torch(
        PromptBatchDataset(debug_store, spec, frames=DRAW_FRAMES, batch_size=8, seed=1, tasks_per_batch=4)[0], "cpu"
    )
    index = batch["context_index"]
    repeated = dict(batch)
    repeated["context"] = index_contexts(batch["context"], index)
    repeated["context_index"] = torch.arange(8)
    grouped = model(batch, torch.Generator().manual_seed(0))
    each = model(repeated, torch.Generator().manual_seed(0))
    torch.testing.assert_close(grouped, each, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("method", ["bpp", "goal_image", "icrt"])
def test_relative_actions_round_trip(debug_store, method):
    model = _model(debug_store, method, action_relative_to=RELATIVE[method])
    assert model.relative_dims == 2
    actions = torch.rand(3, 16, 3) * 400
    origin = torch.rand(3, 1, 2) * 400
    x = model.normalize_actions(actions, origin)
    torch.testing.assert_close(model.unnormalize_actions(x, origin), actions, rtol=1e-5, atol=1e-3)
    # Offsets, not positions: moving the actions and the origin together changes nothing but the pen stays absolute.
    shifted = actions.clone()
    shifted[..., :2] += 50
    torch.testing.assert_close(model.normalize_actions(shifted, origin + 50), x, rtol=1e-5, atol=1e-5)
    assert torch.allclose(x[..., 2], model.normalizer.normalize("action", actions)[..., 2])


def test_relative_actions_need_an_observed_key(debug_store):
    with pytest.raises(ValueError, match="must be an observed low-dimensional key"):
        _model(debug_store, "bpp", action_relative_to="no_such_key")


@pytest.mark.parametrize("method", ["bpp", "goal_image", "icrt"])
def test_relative_grouped_training_saves_loads_and_acts(debug_store, tmp_path, method):
    m = get_method(method)
    cfg = TrainConfig(
        data=debug_store.path,
        out=tmp_path / "run",
        method=method,
        steps=2,
        batch_size=4,
        tasks_per_batch=2,
        save_every=2,
        workers=0,
        warmup_steps=1,
    )
    train(cfg, replace(config(m.name), action_relative_to=RELATIVE[method]), progress=False)
    agent = load_agent(tmp_path / "run")
    assert agent.model.relative_dims == 2
    from helpers import rollout

    result = rollout(agent, debug_store, 0, 0.3, seed=0, max_steps=30)
    assert 0 < result.steps <= 30 and np.isfinite(result.best_chamfer)


class _Oracle(torch.nn.Module):
    """A decoder network that knows the clean chunk: from a noised chunk it returns exactly what `kind` asks for."""

    def __init__(self, clean: torch.Tensor, alphas_cumprod: torch.Tensor, kind: str):
        super().__init__()
        self.clean, self.alphas, self.kind = clean, alphas_cumprod, kind

    def forward(self, noisy, steps, cond):
        alpha = self.alphas[steps][:, None, None]
        eps = (noisy - alpha**0.5 * self.clean) / (1 - alpha) ** 0.5
        return {
            "epsilon": eps,
            "sample": self.clean,
            "v_prediction": alpha**0.5 * eps - (1 - alpha) ** 0.5 * self.clean,
        }[self.kind]


@pytest.mark.parametrize("kind", PREDICTION_TYPES)
@pytest.mark.parametrize("sampler", ["ddim", "ddpm"])
def test_each_prediction_type_trains_on_and_samples_with_its_own_target(kind, sampler):
    """A network that predicts the right quantity has zero loss and denoises any noise to the clean chunk: the loss's
    target and the sampler's reading of the output are the same quantity, for each prediction type."""
    cfg = replace(DEBUG_DIFFUSION, prediction_type=kind, sampler=sampler)
    head = DiffusionHead(cfg, action_dim=2, cond_dim=3)
    clean = torch.rand(4, 16, 2, generator=torch.Generator().manual_seed(0)) * 1.6 - 0.8  # inside the clip range
    head.net = _Oracle(clean, head.alphas_cumprod, kind)
    cond = torch.zeros(4, 3)
    assert head.loss(clean, cond, generator=torch.Generator().manual_seed(1)) < 1e-10
    sampled = head.sample(cond, (16, 2), generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(sampled, clean, rtol=0, atol=1e-4)
    wrong = "sample" if kind != "sample" else "epsilon"
    head.net = _Oracle(clean, head.alphas_cumprod, wrong)
    assert head.loss(clean, cond, generator=torch.Generator().manual_seed(1)) > 1e-3  # the test tells them apart


def test_the_noise_scale_scales_the_samplers_starting_noise_and_zero_gives_one_chunk():
    """A head whose noise scale is s samples from noise x as a plain head samples from s * x; at 0, DDIM gives the
    same chunk whatever the noise. Set by the agent, refused by a model without a diffusion decoder."""
    torch.manual_seed(0)
    head = DiffusionHead(DEBUG_DIFFUSION, action_dim=2, cond_dim=3).eval()
    cond = torch.randn(3, 3, generator=torch.Generator().manual_seed(1))
    a, b = (torch.randn(3, 16, 2, generator=torch.Generator().manual_seed(s)) for s in (2, 3))
    plain = head.sample(cond, (16, 2), noise=0.5 * a)
    head.set_noise_scale(0.5)
    torch.testing.assert_close(head.sample(cond, (16, 2), noise=a), plain, rtol=0, atol=0)
    head.set_noise_scale(0.0)
    torch.testing.assert_close(head.sample(cond, (16, 2), noise=a), head.sample(cond, (16, 2), noise=b))
    head.set_noise_scale(1.0)
    assert not torch.allclose(head.sample(cond, (16, 2), noise=a), head.sample(cond, (16, 2), noise=b))
    with pytest.raises(ValueError, match="noise_scale"):
        head.set_noise_scale(-0.1)


def test_the_agent_and_the_protocol_set_the_noise_scale(debug_store):
    model = BPPModel(config("bpp"), debug_store.stats)
    assert model.head.cfg.noise_scale == 1.0
    PolicyAgent(model, **Protocol(noise_scale=0.25).agent_options())
    assert model.head.cfg.noise_scale == 0.25
    PolicyAgent(model, **Protocol().agent_options())  # None: the model's own is kept
    assert model.head.cfg.noise_scale == 0.25
    with pytest.raises(ValueError, match="no diffusion decoder"):
        PolicyAgent(ICRTModel(config("icrt"), debug_store.stats), noise_scale=0.5)
    with pytest.raises(ValueError, match="noise_scale"):
        Protocol(noise_scale=3.0)
