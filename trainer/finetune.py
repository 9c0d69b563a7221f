"""Fine-tuning: a run that starts from another run's network (``--init``).

The new run takes the network whole from the checkpoint: the weights it renders with (the
moving average when it kept one, ``trainer.checkpoint.weights``), its shape (``--model``,
``--width``, ``--skips``, ``--roughness-channels``) and its tonemap (``--exposure``), so
that its targets are the ones the network learnt. Everything else starts afresh: the
optimizer, the step count, the rate schedule, the moving average (from the loaded weights),
the best score. The held-out split keeps the checkpoint's: on the stores both runs train on,
the materials it held out stay held out and those it trained on stay in training, so the
new run's held-out scores measure materials neither run has seen; materials it never saw
are drawn at ``--holdout-fraction``.

``--init`` matters only at a run's start: a run folder that holds checkpoints resumes from
them (as a restarted pod or torchrun attempt does), whatever ``--init`` says.
"""

from __future__ import annotations

import dataclasses

from storage.catalog import Catalog
from trainer import checkpoint
from trainer.config import TrainConfig, absolute_store


def init_state(cfg: TrainConfig, resumed: dict | None) -> dict | None:
    """The checkpoint ``cfg.init`` names, for a run that starts now (``None`` otherwise)."""
    if cfg.init is None or resumed is not None:
        return None
    return checkpoint.load(cfg.init)


def with_network(cfg: TrainConfig, init: dict | None) -> TrainConfig:
    """``cfg`` with the network options of ``init`` (as given without one), so that the
    run's config says what it trains."""
    if init is None:
        return cfg
    net, tonemap = init["model_config"], init["tonemap"]
    return dataclasses.replace(
        cfg,
        model=net["arch"],
        width=net["width"],
        skips=net["skips"],
        roughness_channels=net["roughness_channels"],
        exposure=tonemap["exposure"],
    )


def kept_split(init: dict | None) -> dict[str, tuple[list[int], list[int]]] | None:
    """What :meth:`Catalog.snapshot` keeps of ``init``'s split: per store (named as the
    trainer names stores), the shards it took and the materials it held out."""
    if init is None:
        return None
    was = Catalog.from_dict(init["catalog"])
    return {
        absolute_store(url): (shards, heldout)
        for url, shards, heldout in zip(was.urls, was.shards, was.heldout, strict=True)
    }


def mismatch(init: dict, path: str, catalog: Catalog) -> str | None:
    """Why ``init`` cannot be fine-tuned on ``catalog`` (``None``: it can)."""
    trained = init["model_config"]["resolution"]
    if trained != catalog.resolution:
        return (
            f"{path} renders {trained}², the stores hold {catalog.resolution}²: fine-tune "
            "on stores of its resolution"
        )
    return None
