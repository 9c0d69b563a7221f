"""The training run's settings, one typed dataclass, and the CLI options made from it.

A *recipe* (:data:`RECIPES`, ``--recipe``) gives the defaults of the settings that decide
how much the network learns per image: its inputs and shape, the loss, the batch, the
learning rate and its schedule, the weight average. Any of them given on its own wins over
the recipe. ``shaderball`` (the default) is the recipe ``benchmarks/learning.py`` chose for what
it learns per image pass (docs/training.md, "Recipes"); ``paper`` is the paper's
network and settings (batch 6, Adam β 0.9/0.999, L1 + VGG16 relu3_3, 30 epochs) with the
authors' code's rate (1e-3; the paper prints 1e-2). ``trainer train`` and ``trainer launch``
share these options; ``launch`` turns a config back into the exact ``trainer train``
arguments (:func:`to_argv`).
"""

from __future__ import annotations

import math
import os
from dataclasses import MISSING, asdict, dataclass, field, fields

import click

from trainer.cues import CUES, check_cues, ordered
from trainer.precision import PRECISIONS
from trainer.training.schedule import SCHEDULES

LOSSES = ("l1+vgg", "l1", "l1+msssim", "l1+flip")
NORMS = ("batch", "group")


#: the options that shape the network: a run started from --init takes them from it
NETWORK = (
    "model", "width", "skips", "roughness_channels", "exposure", "inputs", "norm", "head",
    "residual", "decoder_convs",
)  # fmt: skip

#: every recipe's settings (the fields a recipe leaves to its default are left out); a
#: field given its own value keeps it
RECIPES = {
    "shaderball": {
        "batch_size": 4,
        "lr": 2e-3,
        "lr_schedule": "onecycle",
        "warmup_steps": 0,
        "loss": "l1+msssim",
        "width": 64,
        "inputs": (
            "paint",
            "geometry",
            "light",
            "normal",
            "reflection",
            "shadow",
            "ambient",
            "shade",
        ),
        "norm": "group",
        "head": False,
        "residual": False,
        "decoder_convs": 1,
        "ema_decay": 0.999,
    },
    "paper": {
        "batch_size": 6,
        "lr": 1e-3,
        "lr_schedule": "constant",
        "warmup_steps": 0,
        "loss": "l1+vgg",
        "width": 64,
        "inputs": (),
        "norm": "batch",
        "head": False,
        "residual": False,
        "decoder_convs": 1,
        "ema_decay": 0.0,
    },
}
DEFAULT_RECIPE = "shaderball"
#: the recipe settings that --model zf (Zsolnai-Fehér's baseline) takes from the paper's
ZF_PLAIN = ("inputs", "norm", "head", "residual", "decoder_convs")
#: a checkpoint whose config names no recipe was trained before recipes: the paper's
LEGACY_RECIPE = "paper"


def parse_inputs(value) -> tuple[str, ...]:
    """``--inputs`` as given (``a,b,c``, ``none``, or a sequence) → the cues, in order."""
    if isinstance(value, str):
        value = () if value.strip() in ("", "none") else value.split(",")
    cues = tuple(v.strip() for v in value)
    check_cues(cues)
    return ordered(cues)


def recipe_help(name: str) -> str:
    """What each recipe sets ``name`` to, for its option's help."""
    said = []
    for recipe, values in RECIPES.items():
        v = values[name]
        if isinstance(v, tuple):
            v = ",".join(v) or "none"
        elif isinstance(v, bool):
            v = "on" if v else "off"
        said.append(f"{recipe}: {v}")
    return "[default: the recipe's; " + "; ".join(said) + "]"


def _opt(default, help: str, **extra):
    return field(default=default, metadata={"help": help, **extra})


def absolute_store(url: str) -> str:
    """A local store path made absolute, so that the run's config and checkpoints name a
    store that ``trainer eval``, the viewer and the dashboard find from any folder; a URL
    (``s3://``, ``file://``) as given."""
    return url if "://" in url else os.path.abspath(url)


def _at_least(n: int) -> tuple:
    return (lambda v: v >= n, f"at least {n}")


def _one_of(names: tuple) -> tuple:
    return (lambda v: v in names, "one of " + ", ".join(map(str, names)))


_UNIT = (lambda v: 0 <= v < 1, "in [0, 1)")
#: what each :class:`TrainConfig` field must be: a test of its value, and the rule as the
#: error states it, with the field's flag ("--batch-size must be at least 1, not 0")
RULES = {
    "epochs": _at_least(1),
    "batch_size": _at_least(1),
    "lr": (lambda v: v > 0, "above 0"),
    "lr_schedule": _one_of(SCHEDULES),
    "warmup_steps": _at_least(0),
    "ema_decay": _UNIT,
    "weight_decay": _at_least(0),
    "width": _at_least(1),
    "decoder_convs": _at_least(1),
    "roughness_channels": _one_of((1, 3)),
    "seed": _at_least(0),
    "holdout_seed": _at_least(0),
    "perceptual_weight": _at_least(0),
    "workers": _at_least(0),
    "checkpoint_every": _at_least(1),
    "checkpoint_seconds": (lambda v: 0 <= v < math.inf, "0 or more"),
    "log_every": _at_least(1),
    "val_every": _at_least(0),
    "val_samples": _at_least(0),
    "keep": _at_least(1),
    "shuffle_buffer": _at_least(1),
    "holdout_fraction": _UNIT,
    "max_steps": (lambda v: v is None or v >= 1, "at least 1"),
    "time_limit": (lambda v: v is None or v > 0, "above 0"),
    "loss": _one_of(LOSSES),
    "precision": _one_of(PRECISIONS),
}


@dataclass
class TrainConfig:
    store: tuple[str, ...] = _opt((), "store to train on (path or s3://); repeat for several")
    recipe: str = _opt(
        DEFAULT_RECIPE,
        "the defaults of the settings marked 'the recipe's': shaderball (learns the most per "
        "image pass, docs/training.md) or paper (the paper's network and settings)",
        choices=tuple(RECIPES),
    )
    out: str = _opt("runs/latest", "run folder: checkpoints/, log.jsonl, tb/ (TensorBoard)")
    epochs: int = _opt(30, "epochs over the training split")
    batch_size: int | None = _opt(None, "images per step on each rank", recipe=True)
    lr: float | None = _opt(None, "Adam's (peak) learning rate", recipe=True)
    lr_schedule: str | None = _opt(
        None,
        "constant; cosine: half a cosine from --lr to 0 over the run; onecycle: up from "
        "--lr/25 to --lr over the first 30 %, then half a cosine to 0",
        choices=SCHEDULES,
        recipe=True,
    )
    warmup_steps: int | None = _opt(
        None, "steps of linear warm-up to --lr at the start (constant, cosine)", recipe=True
    )
    ema_decay: float | None = _opt(
        None,
        "keep a moving average of the weights with this decay (0: none): what the "
        "checkpoints render with and the held-out scores measure, beside the trained "
        "weights (trainer.training.ema)",
        recipe=True,
    )
    beta1: float = _opt(0.9, "Adam β1")
    beta2: float = _opt(0.999, "Adam β2")
    weight_decay: float = _opt(
        0.0,
        "decoupled weight decay (AdamW, Loshchilov & Hutter 2019): each step shrinks every "
        "weight by rate x this (0: plain Adam)",
    )
    clip: float = _opt(1.0, "clip the gradient norm to this (0: no clipping)")
    loss: str | None = _opt(
        None,
        "l1+vgg (the paper's: L1 + VGG16 relu3_3 features), l1 (its ablation), l1+msssim "
        "(0.84 MS-SSIM + 0.16 L1, Zhao et al. 2017; no weights needed), l1+flip (0.84 LDR-FLIP "
        "+ 0.16 L1: trainer eval's perceptual score as the loss)",
        choices=LOSSES,
        recipe=True,
    )
    perceptual_weight: float = _opt(1.0, "weight of the VGG16 relu3_3 feature loss")
    vgg_weights: str | None = _opt(
        None, "torchvision VGG16 state dict (.pth); default: the torch hub cache"
    )
    model: str = _opt(
        "unet",
        "unet (the paper's) or zf (Zsolnai-Fehér et al. 2018's baseline: the material's values "
        "to an image, no light input; train it on a --fixed-sun store)",
        choices=("unet", "zf"),
    )
    width: int | None = _opt(None, "channels of the first U-Net level", recipe=True)
    inputs: tuple[str, ...] | None = _opt(
        None,
        "scene cues the network takes beside the maps, comma-separated, or none: "
        + ", ".join(CUES)
        + " (trainer.scene; all but light need a store rendered with geometry buffers)",
        recipe=True,
    )
    norm: str | None = _opt(
        None, "batch (BatchNorm) or group (GroupNorm)", choices=NORMS, recipe=True
    )
    head: bool | None = _opt(
        None, "a full-resolution block over the decoder and the inputs", recipe=True
    )
    residual: bool | None = _opt(
        None, "draw the image as a correction of the shade cue", recipe=True
    )
    decoder_convs: int | None = _opt(
        None,
        "3x3 conv blocks at each decoder level (the paper's 1): depth where the channels are few",
        recipe=True,
    )
    skips: bool = _opt(True, "skip connections (--no-skips: the paper's ablation)")
    roughness_channels: int = _opt(
        1, "1, or 3 to repeat roughness as the authors' 12-channel input"
    )
    exposure: float = _opt(1.0, "tonemap exposure in stops (stored in checkpoints)")
    seed: int = _opt(0, "seed of the init and the shuffle")
    holdout_fraction: float = _opt(0.02, "materials held out for eval (the paper: 1,000 of 50,000)")
    holdout_seed: int = _opt(
        0, "seed of the held-out draw (apart from --seed: runs of other seeds hold out the same)"
    )
    shuffle_buffer: int = _opt(256, "samples shuffled together after the shard shuffle")
    workers: int = _opt(2, "DataLoader worker processes per rank")
    preload: bool = _opt(
        False,
        "read the training split into the device's memory once and take every batch from "
        "there, with no loader workers, each sample's target and scene cues made once: for "
        "stores that fit (a 64² store of 2,500 samples takes about 100 MB, and the default "
        "network's cues of it 1.5 GB, made in each step instead above 4 GiB), on a GPU whose "
        "steps a loader cannot keep up with",
    )
    checkpoint_every: int = _opt(500, "steps between checkpoints (and at each epoch's end)")
    checkpoint_seconds: float = _opt(
        0.0,
        "at an epoch's end, save only once this many seconds have passed since the last "
        "checkpoint (0: at every epoch's end); the run's end, a stop and a new best score "
        "always save: for runs of many short epochs, whose saves would outlast their steps",
    )
    keep: int = _opt(3, "checkpoints kept")
    log_every: int = _opt(10, "steps between log lines and TensorBoard points")
    val_every: int = _opt(
        0,
        "steps between held-out PSNR / SSIM scores (val.jsonl, TensorBoard val/), besides the "
        "one at each epoch's end (0: at each epoch's end only)",
    )
    val_samples: int = _opt(
        64, "held-out samples scored, evenly spaced over the held-out split (0: no scores)"
    )
    init: str | None = _opt(
        None,
        "fine-tune: start from this run's or checkpoint's network (its weights, shape and "
        "tonemap) with a fresh optimizer at step 0; the materials it trained on stay in "
        "training and those it held out stay held out",
    )
    max_steps: int | None = _opt(None, "stop (with a checkpoint) after this many steps in all")
    time_limit: float | None = _opt(
        None,
        "stop (with a checkpoint; --resume goes on) once this process has trained this many "
        "seconds: checked after every step on one process, at each epoch's end under torchrun",
    )
    resume: bool = _opt(False, "continue from the run folder's latest checkpoint")
    device: str = _opt(
        "auto", "auto (CUDA if present), cuda or cpu", choices=("auto", "cuda", "cpu")
    )
    precision: str = _opt(
        "auto",
        "auto: bf16 autocast where the device has bf16 arithmetic (CUDA, a CPU with AMX or "
        "AVX512-BF16), else fp32; bf16; fp32 (the weights and the optimizer are fp32 in "
        "every case)",
        choices=PRECISIONS,
    )
    log_samples: bool = _opt(False, "record each rank's sample ids in samples/rank-R.txt")

    def __post_init__(self) -> None:
        if self.recipe not in RECIPES:
            raise ValueError(f"--recipe must be one of {', '.join(RECIPES)}, not {self.recipe!r}")
        for name, value in RECIPES[self.recipe].items():
            if getattr(self, name) is None:
                zf = self.model == "zf" and name in ZF_PLAIN  # the baseline has no such parts
                setattr(self, name, RECIPES["paper"][name] if zf else value)
        self.inputs = parse_inputs(self.inputs)
        self.store = tuple(absolute_store(u) for u in self.store)
        self.init = None if self.init is None else os.path.abspath(self.init)
        for name, (ok, rule) in RULES.items():
            value = getattr(self, name)
            if not ok(value):
                raise ValueError(f"{_flag(name)} must be {rule}, not {value!r}")
        if again := [u for i, u in enumerate(self.store) if u in self.store[:i]]:
            raise ValueError(f"--store {again[0]} is given twice")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["store"] = list(self.store)
        d["inputs"] = list(self.inputs)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        """The config ``to_dict`` made; one kept before recipes is the paper recipe's."""
        known = {f.name for f in fields(cls)}
        d = {"recipe": LEGACY_RECIPE, **d}
        return cls(**{k: v for k, v in d.items() if k in known})


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def options(command):
    """Decorate a click command with one option per :class:`TrainConfig` field."""
    for f in reversed(fields(TrainConfig)):
        help_, choices = f.metadata["help"], f.metadata.get("choices")
        default = f.default if f.default is not MISSING else None
        if f.metadata.get("recipe"):
            help_ = f"{help_} {recipe_help(f.name)}"
        if f.name == "store":
            opt = click.option("--store", "store", multiple=True, help=help_)
        elif f.type in ("bool", "bool | None"):
            on = _flag(f.name)
            off = "--no-" + f.name.replace("_", "-")
            opt = click.option(
                f"{on}/{off}", f.name, default=default, show_default=True, help=help_
            )
        else:
            kind = {"int": int, "float": float}.get(f.type.removesuffix(" | None"), str)
            if choices:
                kind = click.Choice(choices)
            opt = click.option(
                _flag(f.name), f.name, type=kind, default=default,
                show_default=default is not None, help=help_,
            )  # fmt: skip
        command = opt(command)
    return command


def to_argv(cfg: TrainConfig) -> list[str]:
    """The ``trainer train`` arguments that give back ``cfg`` (defaults, and the recipe's,
    left out)."""
    argv: list[str] = []
    recipe = RECIPES[cfg.recipe]
    for f in fields(TrainConfig):
        value = getattr(cfg, f.name)
        if f.name == "store":
            for s in value:
                argv += ["--store", s]
        elif value != recipe.get(f.name, f.default):
            argv += option_argv(f.name, value)
    return argv


def option_argv(name: str, value) -> list[str]:
    """The ``trainer train`` arguments that set field ``name`` to ``value``."""
    if name == "inputs":
        return ["--inputs", ",".join(value) or "none"]
    if isinstance(value, bool):
        return [_flag(name) if value else "--no-" + name.replace("_", "-")]
    return [_flag(name), str(value)]
