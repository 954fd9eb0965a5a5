"""A compiled training step (`bpp train --compile`): batches padded to a few shapes give the same loss, the loss of a
diffusion method is one graph (what a GPU can record and replay), and a compiled run learns as the eager one."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from bpp.data.contexts import padded_length
from bpp.data.prompt_dataset import PromptBatchDataset
from bpp.nn.text import padded_tokens
from bpp.policies.config import DEBUG_DIFFUSION
from bpp.policies.diffusion import DiffusionHead
from bpp.policies.model import keep_eager
from bpp.policies.registry import get_method
from bpp.train import TrainConfig, train
from bpp.utils import to_torch
from helpers import DRAW_FRAMES, config, pretrained_text_folder


def _model(store, method: str, **overrides):
    torch.manual_seed(0)
    m = get_method(method)
    return m.model_cls(replace(config(m.name), **overrides), store.stats)


def test_padded_length_rounds_up_within_the_limit():
    assert padded_length(37, 0, 800) == 37  # 0: no extra padding
    assert padded_length(37, 50, 800) == 50
    assert padded_length(100, 50, 800) == 100
    assert padded_length(790, 100, 800) == 800  # the last bucket stops at the limit
    assert padded_length(800, 100, 800) == 800


@pytest.mark.parametrize("method", ["bpp", "icrt"])
def test_padding_changes_no_loss(debug_store, method):
    """The same draws, padded to a multiple of 64 steps: prompts (and ICRT's whole episodes) grow, the loss does not."""
    model = _model(debug_store, method).eval()
    spec = model.data_spec()

    def batch(pad: int) -> dict:
        data = PromptBatchDataset(
            debug_store, spec, frames=DRAW_FRAMES, batch_size=8, seed=3, tasks_per_batch=2, pad_to_multiple=pad
        )
        return data[0]

    plain, padded = batch(0), batch(64)
    steps = padded["context"]["valid"].shape[1]
    assert steps > plain["context"]["valid"].shape[1]
    assert steps % 64 == 0 or steps == spec.max_prompt_steps
    assert padded["context"]["valid"].sum() == plain["context"]["valid"].sum()  # padding is not valid
    stride = spec.context_obs_stride
    for key, obs in padded["context"]["obs"].items():
        assert obs.shape[1] == -(-steps // stride), key
    if spec.samples == "episodes":
        length = padded["action"].shape[1]
        assert length > plain["action"].shape[1] and (length % 64 == 0 or length == spec.max_episode_steps)
    losses = [model(to_torch(b, "cpu"), torch.Generator().manual_seed(0)) for b in (plain, padded)]
    torch.testing.assert_close(losses[0], losses[1], rtol=1e-5, atol=1e-6)


def test_pad_to_multiple_must_not_be_negative(debug_store):
    with pytest.raises(ValueError, match="pad_to_multiple"):
        PromptBatchDataset(debug_store, _model(debug_store, "bpp").data_spec(), frames=DRAW_FRAMES, pad_to_multiple=-1)


def test_auto_padding_is_off_eager_and_an_eighth_of_the_prompt_limit_compiled(debug_store, tmp_path):
    spec = _model(debug_store, "bpp").data_spec()
    assert TrainConfig(data=tmp_path).padding(spec) == 0
    steps = TrainConfig(data=tmp_path, compile="default").padding(spec)
    assert steps % spec.context_obs_stride == 0 and steps * 8 >= spec.max_prompt_steps > steps * 7
    assert TrainConfig(data=tmp_path, compile="default", pad_to_multiple=20).padding(spec) == 20
    with pytest.raises(ValueError, match="compile"):
        TrainConfig(data=tmp_path, compile="fast")


@pytest.mark.slow
@pytest.mark.parametrize(
    ("method", "overrides"),
    [("bpp", {}), ("goal_image", {}), ("icrt", {"max_tokens": 20})],  # ICRT: rollouts longer than fit after the prompt
)
def test_the_loss_is_one_graph_and_its_draws_are_the_generators(debug_store, method, overrides):
    """`torch.compile(fullgraph=True)` fails on any graph break: the whole loss and its backward are captured, so a
    GPU can replay them as CUDA graphs. The draws made before the loss are those the loss would make itself.

    ICRT's eager loss runs only the rollout steps that fit after the batch's longest prompt; the compiled one runs
    them all and masks the rest. With a context of 20 tokens the cut is real, and the two losses must agree."""
    model = _model(debug_store, method, **overrides).train()
    spec = model.data_spec()
    batch = to_torch(
        PromptBatchDataset(debug_store, spec, frames=DRAW_FRAMES, batch_size=8, seed=2, pad_to_multiple=100)[0], "cpu"
    )
    if method == "icrt":
        prompts = batch["context"]["valid"][batch.get("context_index", slice(None))]  # those the rollouts follow
        prompt_tokens = 2 * -(-prompts.sum(1).max() // model.cfg.chunk_len)
        assert batch["valid"].sum(1).max() > (model.cfg.max_tokens - prompt_tokens) // 2 * model.cfg.chunk_len
    noise = model.draw_noise(batch, torch.Generator().manual_seed(5))
    eager = model(batch, noise=noise)
    torch.testing.assert_close(eager, model(batch, torch.Generator().manual_seed(5)), rtol=0, atol=0)
    eager.backward()
    expected = [p.grad.clone() for p in model.parameters()]
    model.zero_grad(set_to_none=True)
    torch._dynamo.reset()
    loss = torch.compile(model, backend="aot_eager", fullgraph=True)(batch, noise=noise)
    loss.backward()
    torch.testing.assert_close(loss, eager, rtol=1e-5, atol=1e-6)
    for p, g in zip(model.parameters(), expected, strict=True):
        torch.testing.assert_close(p.grad, g, rtol=1e-4, atol=1e-6)


FACTORIES = {torch.arange, torch.full, torch.zeros, torch.ones, torch.empty, torch.tensor, torch.randn, torch.rand}


@pytest.mark.slow
@pytest.mark.parametrize("method", ["bpp", "goal_image", "language", "icrt"])
def test_the_compiled_loss_reads_only_the_model_and_the_batch(debug_store, described_store, method):
    """What keeps a compiled loss on a GPU from being replayed as a CUDA graph: a CPU tensor read from outside the
    model's parameters and buffers (once, the noise scheduler's schedule) or made without a device inside it. The
    graph captured here, on a CPU, shows both: graph inputs other than the module's tensors and the call's, tensor
    factories without a device, and moves to a device."""
    store = described_store if method == "language" else debug_store
    model = _model(store, method).train()
    batch = to_torch(
        PromptBatchDataset(store, model.data_spec(), frames=DRAW_FRAMES, batch_size=4, seed=2, pad_to_multiple=100)[0],
        "cpu",
    )
    found = []

    def inspect(graph_module, example_inputs):
        for node in graph_module.graph.nodes:
            where = node.meta.get("stack_trace", "")[-200:]
            # Inputs: the module's tensors, the call's, symbolic sizes (s0, ...), and what an uncompiled function
            # between two graphs returned (stack...; the instructions' token ids, which must come on the device).
            known = ("_parameters_", "_buffers_", "l_batch_", "l_noise_", "l_stack")
            if node.op == "placeholder" and not any(k in node.name for k in known) and not node.name.startswith("s"):
                found.append(f"graph input {node.name}")
            if node.op == "call_function" and node.target in FACTORIES and "device" not in node.kwargs:
                found.append(f"{node.target.__name__} without a device: {where}")
            targets = [*node.args[1:], *node.kwargs.values()]
            if node.op == "call_method" and node.target == "to" and any(isinstance(t, torch.device) for t in targets):
                found.append(f"a tensor moved to a device (from the CPU, on a GPU): {where}")
        return graph_module.forward

    torch._dynamo.reset()
    torch.compile(keep_eager(model), backend=inspect)(batch, noise=model.draw_noise(batch))
    assert not found, found


def test_training_noise_is_the_ddpm_schedulers():
    """The loss noises samples with its own copy of the schedule (a buffer), as diffusers' DDPM scheduler does."""
    torch.manual_seed(0)
    head = DiffusionHead(DEBUG_DIFFUSION, action_dim=2, cond_dim=5)
    actions, cond = torch.randn(6, 16, 2), torch.randn(6, 5)
    noise = head.draw_noise(actions.shape, actions.device, torch.Generator().manual_seed(0))
    noisy = head.train_scheduler.add_noise(actions, noise["noise"], noise["timesteps"])
    expected = torch.nn.functional.mse_loss(head.net(noisy, noise["timesteps"], cond), noise["noise"])
    torch.testing.assert_close(head.loss(actions, cond, noise=noise), expected, rtol=0, atol=0)


@pytest.mark.slow
def test_a_compiled_language_loss_is_not_compiled_again_for_each_instruction(described_store):
    """Instructions are tokenized outside the compiled graph (`keep_eager`, which `bpp train --compile` applies):
    were the strings traced, each new instruction would be a constant of a new graph. Four batches of different
    instructions: one graph, and one more for a new token length (after which the length is a dynamic dimension)."""
    model = _model(described_store, "language").train()
    data = PromptBatchDataset(
        described_store, model.data_spec(), frames=DRAW_FRAMES, batch_size=4, seed=2, tasks_per_batch=2
    )
    lengths = {"eager": set(), "compiled": set()}
    tokenizer = model.tokenizer

    def recorded(texts, max_tokens, multiple=1):
        ids, valid = tokenizer(texts, max_tokens, multiple)
        lengths["eager" if multiple == 1 else "compiled"].add(ids.shape[1])
        return ids, valid

    model.tokenizer = recorded
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    loss = torch.compile(keep_eager(model), backend="aot_eager")
    texts = set()
    for i in range(4):
        batch = to_torch(data[i], "cpu")
        texts.update(batch["context"]["text"])
        noise = model.draw_noise(batch, torch.Generator().manual_seed(i))
        # Compiled, the token ids are padded (masked): the loss is the eager one all the same.
        torch.testing.assert_close(loss(batch, noise=noise), model(batch, noise=noise), rtol=1e-5, atol=1e-6)
    assert len(texts) >= 3
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] <= 3
    # Lengths in steps of 16 tokens: at most max_tokens / 16 CUDA graphs to record under reduce-overhead.
    limit = model.text_encoder.max_tokens
    assert lengths["compiled"] == {padded_tokens(n, 16, limit) for n in lengths["eager"]} != lengths["eager"], lengths


@pytest.mark.parametrize("tokenizer", ["bytes", pytest.param("pretrained", marks=pytest.mark.language)])
def test_token_ids_pad_to_a_multiple_within_the_encoders_limit(tokenizer, tmp_path):
    from bpp.nn.text import ByteTokenizer, PretrainedTokenizer

    if tokenizer == "bytes":
        tokenize = ByteTokenizer()
    else:  # a WordPiece tokenizer, as BERT-like encoders have
        tokenize = PretrainedTokenizer(pretrained_text_folder(tmp_path / "bert", "bert"))
    texts = ["draw a house", "draw the letter b twice, then a star"]
    ids, valid = tokenize(texts, 64)
    padded, padded_valid = tokenize(texts, 64, multiple=16)
    assert padded.shape[1] % 16 == 0 and padded.shape[1] > ids.shape[1]
    assert torch.equal(padded[:, : ids.shape[1]], ids) and torch.equal(padded_valid[:, : ids.shape[1]], valid)
    assert not padded_valid[:, ids.shape[1] :].any()
    assert tokenize(texts, ids.shape[1] + 1, multiple=16)[0].shape[1] == ids.shape[1] + 1  # never past the limit


@pytest.mark.slow
def test_a_compiled_run_logs_the_eager_runs_losses(debug_store, tmp_path, monkeypatch):
    """`bpp train --compile default` on this CPU (inductor's C++ kernels), and `--compile cudagraphs` (no GPU here to
    record on: the captured graph runs eagerly): the same losses as eager, to float
    rounding (the debug preset has no dropout, whose random numbers inductor draws its own way). One prompt shape
    (padded to the model's limit), so it is compiled once."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from torch._inductor import config as inductor

    # Kernels built in this process: inductor's pool of compiling subprocesses, each importing torch, costs this
    # test 40 s on 2 cores (its kernels are few, and cached after the first run).
    monkeypatch.setattr(inductor, "compile_threads", 1)

    cfg = config("bpp", obs="board")
    cfg = replace(cfg, diffusion=replace(cfg.diffusion, down_dims=(32,)))  # one U-Net level: fewer kernels to build
    spec = get_method("bpp").model_cls(cfg, debug_store.stats).data_spec()
    losses = {}
    for mode in ("off", "default", "cudagraphs"):  # cudagraphs: traced and run eagerly on a CPU
        run = tmp_path / mode
        tc = TrainConfig(
            data=debug_store.path, out=run, steps=4, batch_size=8, log_every=1, warmup_steps=2, threads=1,
            compile=mode, pad_to_multiple=spec.max_prompt_steps, device="cpu",  # a GPU's bf16 would differ more
        )  # fmt: skip
        torch._dynamo.reset()
        torch._dynamo.utils.counters.clear()
        assert train(tc, cfg, progress=False).name == "step_00000004"
        graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
        assert graphs == (0 if mode == "off" else 1), (mode, graphs)  # one prompt shape: compiled once
        events = EventAccumulator(str(run / "tb"))
        events.Reload()
        losses[mode] = np.array([e.value for e in events.Scalars("train/loss")])
    assert len(losses["off"]) == 4
    np.testing.assert_allclose(losses["default"], losses["off"], rtol=1e-4)
    np.testing.assert_allclose(losses["cudagraphs"], losses["off"], rtol=1e-4)
