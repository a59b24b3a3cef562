"""Denormals flushed to zero around a network's evaluation: the mode comes and goes with the
block, and a field whose softplus meets denormals gives the same bits with it as without."""

from __future__ import annotations

import contextlib
import threading

import torch
import torch.nn.functional as F

import regnf.neural_fields.field as field_module
from regnf.core.denormals import denormals_flushed, flushing
from regnf.core.threads import one_thread
from regnf.neural_fields import neural_sdf
from regnf.neural_fields.field import FieldInfo
from regnf.neural_fields.neural_sdf import NeuralSDF
from tests.scene_graph.helpers import TINY

EXP_DENORMAL = -87.3
"""exp(x) of float32 is denormal (or zero) below about this."""


def test_the_mode_is_on_in_the_block_only_and_on_this_thread_only() -> None:
    assert not flushing()
    seen = []
    with denormals_flushed():
        assert flushing()
        with denormals_flushed():
            assert flushing()
        assert flushing()  # an inner block leaves the outer one's mode
        other = threading.Thread(target=lambda: seen.append(flushing()))
        other.start()
        other.join()
    assert not flushing() and seen == [True]  # a thread started in the block copies its mode
    with contextlib.suppress(RuntimeError), denormals_flushed():
        raise RuntimeError
    assert not flushing()


def evaluate(field: NeuralSDF, x: torch.Tensor) -> list[torch.Tensor]:
    """SDF, gradient, colour and a second derivative (the eikonal term's gradient) at ``x``."""
    p = x.clone().requires_grad_(True)
    sdf = field.sdf(p)
    (grad,) = torch.autograd.grad(sdf.sum(), p, create_graph=True)
    (second,) = torch.autograd.grad(grad.norm(dim=-1).sub(1.0).square().sum(), p)
    s, g = field.sdf_and_gradient(x)
    return [sdf.detach(), grad.detach(), second, s, g, field.color(x)]


def test_a_field_is_the_same_bits_with_denormals_flushed(monkeypatch) -> None:
    torch.manual_seed(0)
    field = NeuralSDF(TINY, info=FieldInfo("chair", "c"))
    x = (torch.rand(4000, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1) * field.bounds[1]
    # The softplus inputs reach the range where exp(100 h) is denormal: the case at stake.
    lowest: list[float] = []
    softplus = F.softplus
    monkeypatch.setattr(F, "softplus", lambda h, beta=1.0, **k: (lowest.append(float((beta * h).detach().min())),
                                                                    softplus(h, beta=beta, **k))[1])
    field.sdf(x)
    assert min(lowest) < EXP_DENORMAL
    monkeypatch.undo()
    with one_thread():  # every operation on this thread, whose mode is the one set
        flushed = evaluate(field, x)
        for module in (neural_sdf, field_module):
            monkeypatch.setattr(module, "denormals_flushed", contextlib.nullcontext)
        plain = evaluate(field, x)
    for a, b in zip(plain, flushed, strict=True):
        assert torch.equal(a, b)
