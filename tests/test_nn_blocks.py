"""Building blocks: the action decoder's U-Net (its joined FiLM projection reads checkpoints written with one per
block; the CPU's Mish equals torch's) and the prompt encoder's cross-attention (torch's multi-head attention, with
prompts shared by samples through an index)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import load_file

from bpp.nn.attention import DecoderLayer
from bpp.nn.unet1d import ConditionalUnet1D, Mish, mish

PER_BLOCK = Path(__file__).parent / "data" / "unet_film_per_block.safetensors"
"""A U-Net saved by the code that had a FiLM projection per block, with an input and that code's output for it."""


def test_a_checkpoint_with_a_film_projection_per_block_loads_and_gives_its_output():
    saved = load_file(PER_BLOCK)
    weights = {k.removeprefix("weights."): v for k, v in saved.items() if k.startswith("weights.")}
    assert any(".film.1.weight" in k for k in weights)  # the old layout, one projection per block
    net = ConditionalUnet1D(action_dim=3, cond_dim=5, down_dims=(8, 16, 24), kernel_size=3, step_embed_dim=4).eval()
    net.load_state_dict(weights)  # strict: every old key is consumed, every new one filled
    with torch.no_grad():
        out = net(saved["input.actions"], saved["input.steps"], saved["input.cond"])
    torch.testing.assert_close(out, saved["output"], rtol=0, atol=1e-5)
    # A block's rows in the joined layer are that block's old projection, in blocks() order.
    widths = net.film_widths
    assert sum(widths) == net.film.out_features
    start = sum(widths[:3])
    torch.testing.assert_close(net.film.weight[start : start + widths[3]], weights["down.1.1.film.1.weight"])


def test_a_saved_joined_film_reloads_bit_for_bit():
    torch.manual_seed(1)
    net = ConditionalUnet1D(action_dim=2, cond_dim=6, down_dims=(8, 16), kernel_size=5, step_embed_dim=8)
    again = ConditionalUnet1D(action_dim=2, cond_dim=6, down_dims=(8, 16), kernel_size=5, step_embed_dim=8)
    again.load_state_dict(net.state_dict())
    x, steps, cond = torch.randn(3, 4, 2), torch.tensor([0, 5, 9]), torch.randn(3, 6)
    assert torch.equal(net(x, steps, cond), again(x, steps, cond))


@pytest.mark.parametrize("shape", [(64, 256, 4), (7, 1216)])
def test_the_cpu_mish_and_its_gradient_equal_torchs(shape):
    torch.manual_seed(0)
    x = torch.randn(*shape) * 6
    x.view(-1)[:8] = torch.tensor([-100.0, -30.0, -20.0, -1e-3, 0.0, 19.9, 25.0, 100.0])  # the formula's edges
    grad = torch.randn(*shape)
    ours, theirs = x.clone().requires_grad_(), x.clone().requires_grad_()
    y_ours, y_theirs = mish(ours), F.mish(theirs)
    y_ours.backward(grad)
    y_theirs.backward(grad)
    assert y_ours.grad_fn.name() != y_theirs.grad_fn.name()  # the CPU path, not torch's own
    torch.testing.assert_close(y_ours, y_theirs, rtol=1e-5, atol=2e-6)
    torch.testing.assert_close(ours.grad, theirs.grad, rtol=1e-5, atol=2e-5)
    assert torch.isfinite(ours.grad).all()


def test_mish_in_double_precision_is_torchs_own():
    x = torch.randn(5, dtype=torch.float64, requires_grad=True)
    assert mish(x).grad_fn.name() == F.mish(x).grad_fn.name()
    assert torch.equal(Mish()(x), F.mish(x))


@pytest.mark.parametrize("want_attn", [False, True])
def test_cross_attention_is_torchs_multi_head_attention_and_an_index_shares_a_memory(want_attn):
    torch.manual_seed(0)
    layer = DecoderLayer(dim=16, heads=4, mlp_dim=32).eval()
    prompts, queries, length = 3, 5, 7
    memory = torch.randn(prompts, length, 16)
    pad = torch.zeros(prompts, length, dtype=torch.bool)
    pad[1, 4:] = True  # a shorter prompt
    index = torch.tensor([2, 0, 1, 0, 2, 1])  # each prompt serves two samples, in any order
    h = torch.randn(len(index), queries, 16)
    with torch.no_grad():
        theirs, their_weights = layer.cross_attn(
            h, memory[index], memory[index], key_padding_mask=pad[index], need_weights=want_attn
        )
        copied, copied_weights = layer._cross_attend(h, memory[index], pad[index], None, want_attn)
        shared, shared_weights = layer._cross_attend(h, memory, pad, index, want_attn)
    torch.testing.assert_close(copied, theirs, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(shared, theirs, rtol=1e-5, atol=1e-6)
    if want_attn:
        torch.testing.assert_close(shared_weights, their_weights, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(copied_weights, their_weights, rtol=1e-5, atol=1e-6)
        assert (shared_weights[index == 1][..., 4:] == 0).all()  # prompt 1's padding is never attended
        assert (shared_weights[index != 1][..., 4:] > 0).all()
    else:
        assert shared_weights is None and copied_weights is None
