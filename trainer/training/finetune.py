"""Fine-tuning: a run that starts from another run's network (``--init``).

The new run takes the network whole from the checkpoint: the weights it renders with (the
moving average when it kept one, ``trainer.checkpoint.weights``), its shape (``--model``,
``--width``, ``--skips``, ``--roughness-channels``, ``--inputs``, ``--norm``, ``--head``,
``--residual``, ``--decoder-convs``) and its tonemap (``--exposure``), so
that its targets are the ones the network learnt. Everything else starts afresh: the
optimizer, the step count, the rate schedule, the moving average (from the loaded weights),
the best score. The held-out split keeps the checkpoint's: a material it held out stays held
out and one it trained on stays in training, in whichever store the new run finds it (by its
``source_id``: a material rendered again into another store is the same material), so the
new run's held-out scores measure materials neither network has seen; materials it never
saw are drawn at ``--holdout-fraction``. The checkpoint's catalog names those materials,
and the new run's names them with its own, so a chain of fine-tunes keeps every material
any of its networks trained on out of its held-out split. A catalog kept without them is read
from the first run's stores; where they cannot be read the new run says so and draws every
material.

``--init`` matters only at a run's start: a run folder that holds checkpoints resumes from
them (as a restarted pod or torchrun attempt does), whatever ``--init`` says.
"""

from __future__ import annotations

import dataclasses

from storage.catalog import Catalog
from trainer import checkpoint
from trainer.training.config import TrainConfig, absolute_store


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
        inputs=tuple(net.get("inputs", ())),
        norm=net.get("norm", "batch"),
        head=net.get("head", False),
        residual=net.get("residual", False),
        decoder_convs=net.get("decoder_convs", 1),
    )


def kept_materials(init: dict | None) -> tuple[set[str], set[str]] | None:
    """What :meth:`Catalog.snapshot` keeps of ``init``'s split: the ``source_id`` of every
    material it trained on and of every one it held out, as its catalog records them, or
    read from its stores for a catalog kept without them (raises :class:`StoreError` when
    one cannot be read)."""
    if init is None:
        return None
    was = Catalog.from_dict(init["catalog"])
    was.urls = [absolute_store(url) for url in was.urls]
    return was.material_sources()


def mismatch(init: dict, path: str, catalog: Catalog) -> str | None:
    """Why ``init`` cannot be fine-tuned on ``catalog`` (``None``: it can)."""
    trained = init["model_config"]["resolution"]
    if trained != catalog.resolution:
        return (
            f"{path} renders {trained}², the stores hold {catalog.resolution}²: fine-tune "
            "on stores of its resolution"
        )
    return None
