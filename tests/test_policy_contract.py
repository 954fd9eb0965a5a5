"""The method contract the agent and training loop type against, and the agent's guarantees."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.policies.agent import PolicyAgent
from bpp.policies.bpp.config import BPPConfig, PromptConfig
from bpp.policies.bpp.model import BPPModel
from bpp.policies.config import DEBUG_DIFFUSION, ObsConfig
from bpp.policies.icrt.model import ICRTModel
from bpp.policies.normalizer import Normalizer
from bpp.policies.registry import METHODS, PolicyModelContract, get_method, method_names
from helpers import KEYS, config, prompt_from_store


@pytest.mark.parametrize("method", list(METHODS))
def test_every_method_satisfies_the_contract(debug_store, method):
    assert isinstance(get_method(method).model_cls(config(method), debug_store.stats), PolicyModelContract)


def test_size_presets_observe_nothing_until_given_a_benchmarks_observations(debug_store):
    bpp = get_method("bpp")
    with pytest.raises(ValueError, match="observes nothing"):
        BPPModel(bpp.preset("cpu"), debug_store.stats)
    with pytest.raises(ValueError, match="^unknown bpp preset 'large'; choose from debug, cpu, paper$"):
        bpp.preset("large")
    with pytest.raises(ValueError, match="no observation preset 'pixels'"):
        bpp.config("cpu", "pixels", BENCHMARK)
    assert bpp.config("paper", None, BENCHMARK).obs.image_size == 224  # the benchmark's default for that size
    # The state sizes observe the ink drawn so far by default: without it half the rollouts never stop.
    for size in ("debug", "cpu"):
        assert bpp.config(size, None, BENCHMARK).obs.proprio_keys == ("agent_pos", "pen_down", "ink_length")
    goal = get_method("goal_image").config("cpu", "image64", BENCHMARK)
    assert goal.shares_camera_encoder and goal.goal_image_size == 64


def test_the_main_jobs_preset_builds_exactly_its_model(debug_store):
    """The main job's `--preset cpu --obs board` is this BPP config (the image-encoder widths aside, which a
    state-only model does not use), weight for weight: its results hold only for this network."""
    expected = BPPConfig(
        obs=ObsConfig(proprio_keys=("cursor_on_board", "pen_down", "ink_length"), lowdim_fourier_octaves=6),
        prompt=PromptConfig(action_fourier_octaves=6),
        action_key="action_on_board",
    )
    main_job = config("bpp", "cpu", "board")
    assert replace(main_job, obs=replace(main_job.obs, image_features=256, image_widths=(32, 64, 128, 256))) == expected
    models = []
    for cfg in (expected, main_job):
        torch.manual_seed(0)
        models.append(BPPModel(cfg, debug_store.stats).state_dict())
    assert models[0].keys() == models[1].keys()
    assert all(torch.equal(models[0][k], models[1][k]) for k in models[0])


def test_icrt_refuses_replanning_before_its_chunk_is_executed(debug_store):
    model = ICRTModel(config("icrt"), debug_store.stats)
    with pytest.raises(ValueError, match="executes all N=10 actions"):
        PolicyAgent(model, n_action_steps=5)
    assert PolicyAgent(model, n_action_steps=10).n_action_steps == 10


def _first_obs(store, episodes):
    return {k: np.stack([store.episode(e, [k])[k][0] for e in episodes]) for k in KEYS}


@pytest.mark.parametrize("sampler", ["ddpm", "ddim"])
def test_a_rollout_acts_the_same_alone_and_in_a_batch(debug_store, sampler):
    torch.manual_seed(0)
    cfg = replace(config("bpp"), diffusion=replace(DEBUG_DIFFUSION, sampler=sampler))
    agent = PolicyAgent(BPPModel(cfg, debug_store.stats))
    episodes, seeds = [0, 7, 20], [5, 6, 7]
    agent.reset_batch([prompt_from_store(debug_store, e) for e in episodes], seeds)
    together = agent.act_batch(_first_obs(debug_store, episodes))
    for i, (episode, seed) in enumerate(zip(episodes, seeds, strict=True)):
        agent.reset(prompt_from_store(debug_store, episode), seed=seed)
        alone = agent.act_batch(_first_obs(debug_store, [episode]))[0]
        np.testing.assert_allclose(alone, together[i], rtol=1e-5, atol=1e-4)  # float sums differ by batch


def test_an_action_dimension_the_data_never_moves_stays_still_whatever_the_model_outputs():
    stats = {
        "obs": {"min": [0.0, 1.0], "max": [0.0, 3.0]},
        "action": {"min": [-1.0, 0.0, 0.5], "max": [1.0, 0.0, 0.5]},
    }
    normalizer = Normalizer(stats, ["obs", "action"], outputs=("action",))
    out = normalizer.unnormalize("action", torch.tensor([[0.3, -0.9, 1.0]]))[0]
    assert out.tolist() == pytest.approx([0.3, 0.0, 0.5])  # not -0.9 and 1.5: the data never moved them
    # an observed constant is only centred: if it moves at test time, the model still sees it move
    assert normalizer.normalize("obs", torch.tensor([[0.2, 2.0]]))[0].tolist() == pytest.approx([0.2, 0.0])
    # the constants are derived from the statistics the checkpoint keeps, so the saved weights do not repeat them
    assert set(normalizer.state_dict()) == {"obs__scale", "obs__offset", "action__scale", "action__offset"}


def test_other_packages_add_methods_through_entry_points(tmp_path, monkeypatch):
    """A package outside bpp declares a method in the ``bpp.methods`` entry-point group: bpp finds it by name."""
    plugin = tmp_path / "mine"
    plugin.mkdir()
    (plugin / "__init__.py").write_text("from bpp.policies.bpp import MODEL, PRESETS, Config  # noqa: F401\n")
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "__init__.py").write_text("")
    info = tmp_path / "bpp_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: bpp-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[bpp.methods]\nmine = mine\nbroken = broken\ngone = not_there\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert method_names()[: len(METHODS)] == list(METHODS) and {"mine", "broken", "gone"} <= set(method_names())
    method = get_method("mine")
    assert method.name == "mine" and method.preset("debug") == get_method("bpp").preset("debug")
    with pytest.raises(ValueError, match="method 'broken': its package 'broken' lacks Config, MODEL, PRESETS"):
        get_method("broken")
    with pytest.raises(ValueError, match="method 'gone': cannot import its package 'not_there'"):
        get_method("gone")
    with pytest.raises(ValueError, match="unknown method 'nope'; available: bpp, icrt, goal_image, language, broken"):
        get_method("nope")
