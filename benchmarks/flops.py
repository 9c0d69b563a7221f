"""The arithmetic of one training image pass of a network that ``trainer train`` settings
describe: the floating-point operations of its forward pass and of a whole pass (forward,
loss, backward), as PyTorch's FLOP counter counts them.

The count is exact for a given shape (it depends on no value and no machine); it counts
matrix and convolution FLOPs (a multiply-add is two), not the elementwise work of the
normalizations, activations or optimizer. A network with scene cues is counted as ``trainer
train --preload`` trains it: the cues made once per sample, before the step.
"""

from __future__ import annotations

from trainer.training.config import TrainConfig

#: images in the counted batch (the count scales with it; a few keeps the CPU's work small)
BATCH = 4


def network_and_loss(settings: dict, resolution: int):
    """The network ``settings`` (``TrainConfig`` fields) describe, without geometry buffers
    (the count does not depend on their values), and its loss, as ``trainer train`` builds
    them; ``ValueError`` for a loss that needs VGG16 weights."""
    from trainer.networks import build_model
    from trainer.training.losses import RendererLoss, mixed_term
    from trainer.training.train import network_config

    cfg = TrainConfig(store=("-",), **settings)
    if "vgg" in cfg.loss:
        raise ValueError(f"the loss {cfg.loss} needs VGG16 weights")
    model = build_model(network_config(cfg, resolution))
    return model, RendererLoss(mixed=mixed_term(cfg.loss))


def count(settings: dict, resolution: int) -> dict:
    """The parameters of the network ``settings`` describe and its FLOPs per image at
    ``resolution``: ``forward`` and ``pass`` (forward, loss and backward)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    torch.manual_seed(0)
    model, loss = network_and_loss(settings, resolution)
    n = resolution
    maps = torch.rand(BATCH, model.config.in_channels, n, n)
    light = torch.rand(BATCH, 4)
    target = torch.rand(BATCH, 3, n, n)
    cues = None if model.scene is None else model.scene(maps, light).detach()
    with FlopCounterMode(display=False) as counter:
        out = model(maps, light, cues)
        forward = counter.get_total_flops()
        loss(out, target).backward()
        whole = counter.get_total_flops()
    return {
        "parameters": sum(p.numel() for p in model.parameters()),
        "forward": forward / BATCH,
        "pass": whole / BATCH,
    }
