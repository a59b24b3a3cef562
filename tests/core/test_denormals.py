"""Denormals flushed to zero around a network's evaluation: the mode comes and goes with the
block, and a field whose softplus meets denormals gives the same bits with it as without; in
training, on every thread of torch's pool, with the same bits."""

from __future__ import annotations

import contextlib
import threading

import torch
import torch.nn.functional as F
import trimesh

import regnf.fields.field as field_module
from regnf.core.denormals import denormals_flushed, flushing, pool_denormals_flushed
from regnf.core.threads import one_thread
from regnf.fields import neural_sdf
from regnf.fields.field import FieldInfo
from regnf.fields.neural_sdf import NeuralSDF
from regnf.training import optim
from regnf.training.distill import DistillConfig, distill_mesh
from tests.core.helpers import torch_threads
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


def test_the_pool_block_flushes_every_torch_thread_and_restores_them() -> None:
    # exp(-100) is denormal; a million of them are computed by torch's threads in parallel,
    # each its share: all of them come out zero only if every one of those threads flushes.
    x = torch.full((1 << 20,), -100.0)
    with torch_threads(2):
        with pool_denormals_flushed():
            assert flushing() and bool((torch.exp(x) == 0).all())
        # The default mode after it on every thread, whatever a thread had before (a pool thread
        # started inside a flushed evaluation copies its mode).
        assert not flushing() and bool((torch.exp(x) > 0).all())
        with denormals_flushed():  # an outer block's mode is left as it was
            with pool_denormals_flushed():
                pass
            assert flushing()
        assert not flushing()


def test_training_gives_the_same_bits_with_the_pool_flushed(monkeypatch) -> None:
    # The distillation's loop runs in pool_denormals_flushed: the same field as without it.
    mesh = trimesh.creation.box(extents=(0.4, 0.3, 0.5))
    config = DistillConfig(steps=12, batch=512, pool_surface=4000, architecture=TINY)
    fields = []
    with torch_threads(2):
        for block in (optim.pool_denormals_flushed, contextlib.nullcontext):
            monkeypatch.setattr(optim, "pool_denormals_flushed", block)
            field, _ = distill_mesh(mesh, config, info=FieldInfo("box", "b"), progress=False)
            fields.append(field.state_dict())
    flushed, plain = fields
    assert flushed.keys() == plain.keys()
    assert all(torch.equal(flushed[k], plain[k]) for k in flushed)
