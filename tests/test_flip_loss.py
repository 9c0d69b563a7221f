"""LDR-FLIP as a training loss (trainer.training.flip): the values of NVIDIA's flip-evaluator,
which trainer eval scores with, and a gradient that lowers it."""

from __future__ import annotations

import pytest
import torch

from trainer.scoring import flip
from trainer.training.flip import flip_loss, flip_map
from trainer.training.losses import RendererLoss, mixed_term
from trainer.training.separable import filter2d, filter_matrix


def scene(shape, seed=0):
    """Images with flat areas, edges and texture: a bright disc on a ramp, plus fine noise."""
    g = torch.Generator().manual_seed(seed)
    n, _, h, w = shape
    y, x = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
    disc = ((x * x + y * y) < 0.4).float()
    base = torch.stack([0.2 + 0.6 * disc, 0.3 + 0.3 * (x + 1) / 2, 0.5 - 0.3 * disc])
    img = base.expand(n, 3, h, w) + 0.03 * torch.randn(shape, generator=g)
    return img.clamp(0, 1)


@pytest.mark.parametrize("shape", [(3, 3, 64, 64), (2, 3, 48, 80), (1, 3, 128, 128)])
def test_flip_matches_flip_evaluator_per_image(shape):
    target = scene(shape)
    g = torch.Generator().manual_seed(1)
    changes = {
        "noise": (target + 0.05 * torch.randn(shape, generator=g)).clamp(0, 1),
        "blur": torch.nn.functional.avg_pool2d(target, 3, 1, 1, count_include_pad=False),
        "shift": target.roll(2, -1),
        "tint": (target * torch.tensor([1.1, 0.9, 1.0]).view(1, 3, 1, 1)).clamp(0, 1),
    }
    for name, pred in changes.items():
        ours = flip_map(pred, target).flatten(1).mean(1)
        theirs = flip(pred, target)
        assert ours.min() > 0.005, name  # every change is seen
        assert torch.allclose(ours, theirs, atol=2e-5), (name, ours, theirs)


def test_flip_is_zero_for_equal_images_and_its_gradient_stays_finite():
    target = scene((2, 3, 32, 32))
    pred = target.clone().requires_grad_()
    value = flip_loss(pred, target)
    value.backward()
    assert value.item() < 1e-5 and torch.isfinite(pred.grad).all()


def test_gradient_steps_on_flip_lower_flip_as_flip_evaluator_scores_it():
    target = scene((2, 3, 48, 48))
    pred = torch.nn.functional.avg_pool2d(target, 5, 1, 2, count_include_pad=False)
    before = flip(pred, target).mean().item()
    pred = pred.clone().requires_grad_()
    opt = torch.optim.Adam([pred], lr=0.01)
    for _ in range(30):
        opt.zero_grad()
        flip_loss(pred, target).backward()
        opt.step()
    after = flip(pred.detach().clamp(0, 1), target).mean().item()
    assert after < 0.7 * before, (before, after)


def test_the_mixed_losses_by_name():
    assert [mixed_term(x) for x in ("l1+flip", "l1+msssim", "l1", "l1+vgg")] == [
        "flip", "msssim", None, None,
    ]  # fmt: skip
    a, b = scene((2, 3, 32, 32)), scene((2, 3, 32, 32), seed=5)
    loss = RendererLoss(mixed="flip")
    assert float(loss(a, a)) < 1e-5
    expected = 0.84 * flip_loss(b, a) + 0.16 * (b - a).abs().mean()
    assert float(loss(b, a)) == pytest.approx(float(expected), rel=1e-5)
    with pytest.raises(ValueError, match="one of msssim, flip, not 'lpips'"):
        RendererLoss(mixed="lpips")


@pytest.mark.parametrize("pad", ["reflect", "replicate"])
def test_a_filter_matrix_filters_as_a_padded_convolution(pad):
    rows, cols = (0.1, -0.3, 0.5, 0.2, 0.25), (0.0, 0.25, 0.5, 0.25, 0.0)
    x = torch.rand(2, 1, 9, 12)
    kernel = torch.outer(torch.tensor(cols), torch.tensor(rows))[None, None]
    want = torch.nn.functional.conv2d(torch.nn.functional.pad(x, (2, 2, 2, 2), mode=pad), kernel)
    assert torch.allclose(filter2d(x, rows, cols, pad), want, atol=1e-6)
    with pytest.raises(ValueError, match="odd number of taps, not 2"):
        filter_matrix((0.5, 0.5), 4, pad)
