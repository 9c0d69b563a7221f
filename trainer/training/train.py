"""The per-rank training loop (``trainer train``), top to bottom in one file; what it records
is :class:`trainer.training.runlog.RunLog`'s.

``_train`` reads in order: set-up (the checkpoint to resume, the catalog, the model as a
:class:`Trainee`, the stream and the :class:`RunLog`), then each epoch's batches through
:func:`train_step`, logging and :func:`save` at their intervals, and the epoch's end. Each step
is a plain function of what it needs; nothing the loop changes hides in a closure.

One process trains on CPU or one GPU. Under torchrun (``trainer launch``) every rank runs this
same loop as one DDP job: NCCL on GPUs, gloo on CPU. Examples::

    trainer train --store out/demo.zarr --epochs 1 --out runs/demo                # one process
    trainer launch --store out/demo.zarr --epochs 1 --out runs/demo               # torchrun
    trainer launch --nodes 2 --nproc-per-node 8 --rdzv-endpoint head:29400 ...    # 2 nodes x 8

The network (and VGG16) trains in channels_last on every device, in bf16 autocast where the
device has bf16 arithmetic (``--precision``: CUDA, a CPU with AMX or AVX512-BF16), and on
CUDA with cudnn.benchmark. Each rank
reads its own disjoint part of every epoch (``trainer.training.data``); ranks that end an epoch one
batch short are handled by DDP's ``join``.
Rank 0 writes the progress bar, ``RUNDIR/log.jsonl``, TensorBoard events under ``RUNDIR/tb``
and the checkpoints (``trainer.checkpoint``); with ``--ema-decay`` it also keeps the moving
average of the weights (``trainer.training.ema``), updated after every step. A NaN or infinite
gradient norm (identical on every rank, since gradients are all-reduced) stops the run with
:class:`TrainingDiverged` before any checkpoint is written from the diverged weights.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import time
from pathlib import Path

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel as DDP

from render_jobs.screen_uv import FILE as SCREEN_UV_FILE
from shaderball import progress
from shaderball.errors import UserError
from storage.errors import StoreError
from storage.reader import Store
from storage.schema import untrainable
from trainer import checkpoint
from trainer.devices import NoCuda
from trainer.model import ModelConfig
from trainer.networks import build_model
from trainer.precision import autocast_dtype
from trainer.targets import Tonemap, model_inputs
from trainer.training import faults, finetune, shm
from trainer.training.config import NETWORK, TrainConfig, absolute_store, option_argv
from trainer.training.data import Catalog, Preloaded, ShardStream, loader, steps_left
from trainer.training.ema import WeightAverage
from trainer.training.losses import RendererLoss, load_vgg, mixed_term
from trainer.training.runlog import RunLog
from trainer.training.schedule import DECAYING, lr_at, record, resumed_knee, run_steps
from trainer.training.trainee import Rank, Trainee
from trainer.training.validation import Validator


class TrainingDiverged(UserError, RuntimeError):
    """The loss or gradients became NaN or infinite."""


class RunError(UserError, ValueError):
    """The run cannot start as asked (run folder, stores, resolution)."""


class LoaderError(UserError, RuntimeError):
    """The data loader lost batches, or a worker died."""


WORKER_ERROR = (
    "its error is above; when it says no space left on device, a batch did not fit in "
    f"{shm.SHM}: docs/training.md, 'Shared memory'"
)


def train(cfg: TrainConfig) -> dict:
    """Train as ``cfg`` says; returns rank 0's summary (steps, images, seconds, checkpoint)."""
    # ---- distribution and device ------------------------------------------------------------
    distributed = "RANK" in os.environ and "WORLD_SIZE" in os.environ
    rank = int(os.environ.get("RANK", 0))
    world = int(os.environ.get("WORLD_SIZE", 1))
    local_rank = int(os.environ.get("LOCAL_RANK", 0))
    _check_device(cfg)
    use_cuda = cfg.device == "cuda" or (cfg.device == "auto" and torch.cuda.is_available())
    if use_cuda:
        torch.cuda.set_device(local_rank)
        device = torch.device("cuda", local_rank)
    else:
        device = torch.device("cpu")
    if distributed:
        _init_process_group("nccl" if use_cuda else "gloo", rank, world)
    try:
        rk = Rank(rank, world, device, distributed, autocast_dtype(cfg.precision, device.type))
        return _train(cfg, rk)
    except RuntimeError as exc:  # torch raises it wherever the loop is when a worker dies
        if not str(exc).startswith("DataLoader worker"):
            raise
        raise LoaderError(f"{exc} ({WORKER_ERROR})") from None
    finally:
        if distributed:
            dist.destroy_process_group()


def _init_process_group(backend: str, rank: int, world: int) -> None:
    """``init_process_group`` from torchrun's environment, with the rendezvous keys under a
    prefix unique to the torchrun attempt: after a restart, torch 2.13 could otherwise hand
    a rank its peer's address from the failed attempt (gloo: "connection refused")."""
    attempt = os.environ.get("TORCHELASTIC_RESTART_COUNT")
    if attempt is None:
        dist.init_process_group(backend)
        return
    agent = os.environ.get("TORCHELASTIC_USE_AGENT_STORE") == "True"  # torchrun hosts it
    store = dist.TCPStore(
        os.environ["MASTER_ADDR"],
        int(os.environ["MASTER_PORT"]),
        world,
        is_master=not agent and rank == 0,
        multi_tenant=not agent,
    )
    prefixed = dist.PrefixStore(f"shaderball/attempt-{attempt}", store)
    dist.init_process_group(backend, store=prefixed, rank=rank, world_size=world)


def preflight(cfg: TrainConfig, ranks: int = 1) -> None:
    """Every check the ranks would make before training, made once here (no process group):
    the stores open and have committed samples at a usable resolution, the run folder can be
    used (or resumed), the VGG weights load, and the data loaders of the ``ranks`` ranks on
    this node fit in its shared memory (:mod:`trainer.training.shm`). Raises as :func:`train` would,
    the inputs named on the command line (run folder, stores) before the weights; and
    ``--device cuda`` where torch sees no CUDA device."""
    _check_device(cfg)
    state, found = _resume_state(cfg, Path(cfg.out))
    init = finetune.init_state(cfg, state)
    cpu = Rank(0, 1, torch.device("cpu"), False)
    cfg = finetune.with_network(cfg, state if state is not None else init)
    catalog = _catalog(cfg, cpu, state, found, init)
    if state is None and init is None:
        _geometry(cfg, catalog)
    _vgg(cfg)
    _check_shared_memory(cfg, catalog, ranks)


def _check_device(cfg: TrainConfig) -> None:
    if cfg.device == "cuda" and not torch.cuda.is_available():
        raise RunError(str(NoCuda()))


def _vgg(cfg: TrainConfig):
    """The VGG16 the loss uses (None when it uses none); weights given to a loss that
    would not read them are refused rather than ignored."""
    if cfg.loss == "l1+vgg":
        return load_vgg(cfg.vgg_weights)
    if cfg.vgg_weights:
        raise RunError(f"--vgg-weights is read only by --loss l1+vgg, not by {cfg.loss}")
    return None


def _check_shared_memory(cfg: TrainConfig, catalog: Catalog, ranks: int) -> None:
    if cfg.preload:  # no loader workers
        return
    if why := shm.check(catalog.resolution, cfg.batch_size, cfg.workers, ranks):
        raise RunError(why)


def _train(cfg: TrainConfig, rk: Rank) -> dict:
    out = Path(cfg.out)
    state, found = _resume_state(cfg, out)
    init = finetune.init_state(cfg, state)
    asked = cfg  # a resumed run goes on with its network, whatever the options say now
    cfg = finetune.with_network(cfg, state if state is not None else init)
    vgg = _vgg(cfg)  # fails before any work
    catalog = _catalog(cfg, rk, state, found, init)
    if not rk.distributed:  # under torchrun, `trainer launch` checked for every rank at once
        _check_shared_memory(cfg, catalog, 1)
    t = _build(cfg, rk, catalog, state, vgg, init)
    faults.install(t.opt, t.step, rk.master)
    split = catalog.split("train")
    per_epoch = steps_left(len(split), rk.world, cfg.batch_size)
    t.run_steps = run_steps(cfg.epochs, cfg.max_steps, per_epoch)
    was = state.get("schedule") if state is not None else None
    t.knee = resumed_knee(t.step, was, t.run_steps, cfg.warmup_steps, cfg.lr_schedule)
    stream = ShardStream(
        split, batch=cfg.batch_size, seed=cfg.seed, buffer=cfg.shuffle_buffer, world=rk.world,
        rank=rk.rank, epochs=cfg.epochs,
    )  # fmt: skip
    if cfg.preload:
        reader = Preloaded(stream, rk.device, derive=preload_derive(t, len(split)))
    else:
        reader = loader(stream, cfg.workers, pin_memory=rk.cuda)
    notes = _resumed_notes(asked, cfg, state, found)
    notes += _start_notes(cfg, t, catalog, init, found, was)
    log = _start_log(cfg, rk, out, t, catalog, len(split), notes)
    started = time.perf_counter()
    t.deadline = None if cfg.time_limit is None else time.monotonic() + cfg.time_limit
    images = _epochs(cfg, rk, t, stream, reader, log, out)
    log.close(t.model)
    seconds = time.perf_counter() - started
    return {
        "steps": t.step,
        "epoch": t.epoch,
        "images_this_rank": images,
        "seconds": round(seconds, 3),
        "images_per_second": round(images * rk.world / seconds, 2) if seconds > 0 else None,
        "checkpoint": str(log.last_checkpoint or checkpoint.latest(out) or ""),
        "val": log.last_val,
        "best": t.best,
        "timed_out": t.timed_out,
    }


def _start_log(
    cfg: TrainConfig, rk: Rank, out: Path, t: Trainee, catalog: Catalog, samples: int, notes
) -> RunLog:
    """The run's log, its validator on the master, and the lines that open the run (on
    ``samples`` training samples)."""
    log = RunLog(cfg, rk, out)
    if rk.master and cfg.val_samples:
        log.validator = Validator(catalog.split("test"), cfg.val_samples)
    log.start(log.validation_plan())
    for note in notes:
        log.start(note)
    log.start(
        f"training on {samples} samples (held-out materials: "
        f"{sum(map(len, catalog.heldout))}), {rk.world} rank(s) x batch {cfg.batch_size} "
        f"on {rk.device.type} in {rk.precision}, {t.model_cfg.resolution}², loss {cfg.loss}; "
        f"from step {t.step}"
    )
    return log


def _epochs(
    cfg: TrainConfig, rk: Rank, t: Trainee, stream: ShardStream, reader, log: RunLog, out: Path
) -> int:
    """Train epoch by epoch to the end of the run, saving after each; the images this rank saw."""
    samples = len(stream.reader.split)
    images = 0
    batches = None  # one iteration for the whole run: the workers read across epoch ends
    with contextlib.ExitStack() as workers:
        while t.epoch < cfg.epochs and not _stopped(cfg, t):
            if batches is None:
                stream.set_position(t.epoch, t.position)
                batches = iter(reader)
                workers.callback(_join_workers, batches)
            # this rank's batches: one fewer on some ranks
            mine = len(stream.batches(t.epoch, t.position))
            total = steps_left(samples, rk.world, cfg.batch_size, t.position)
            desc = f"epoch {t.epoch + 1}/{cfg.epochs}"
            bar = progress.bar(total=total, desc=desc, disable=not rk.master)
            log.new_window()
            with contextlib.closing(bar):  # the bar ends its line even on errors
                start = t.step
                images += _epoch(cfg, rk, t, itertools.islice(batches, mine), samples, log, bar)
            _check_epoch_whole(cfg, t, t.step - start, mine)
            log.validate(t, bar)  # the epoch's weights, unless the last step just scored them
            if not _stopped(cfg, t):
                t.epoch, t.position = t.epoch + 1, 0
            _check_time(rk, t, epoch_end=True)  # first: a run stopped here saves here
            if epoch_end_saves(cfg, t, log):
                save(cfg, rk, t, out, log)
    return images


def _join_workers(batches) -> None:
    """Stop the loader's worker processes now, whether the run ended or failed.

    Torch stops them when the iterator is collected. After an error the traceback keeps the
    iterator alive until the interpreter exits, after ``multiprocessing`` has removed the
    queues' semaphores; a worker still starting then finds them gone and prints a
    traceback under the run's one-line error."""
    stop = getattr(batches, "_shutdown_workers", None)  # torch's; none without workers
    if stop is not None:
        stop()


def _check_epoch_whole(cfg: TrainConfig, t: Trainee, trained: int, mine: int) -> None:
    """Raise :class:`LoaderError` when the epoch ended on fewer of this rank's batches than
    it has, short of ``--max-steps`` or ``--time-limit``."""
    if trained < mine and not _stopped(cfg, t):
        raise LoaderError(
            f"the data loader ended epoch {t.epoch + 1} after {trained} of this rank's "
            f"{mine} batches: a worker lost the others ({WORKER_ERROR})"
        )


def _resumed_notes(asked: TrainConfig, cfg: TrainConfig, state, found) -> list[str]:
    """Lines on a resumed run that goes on otherwise than ``asked`` says: with the network
    it was trained with (its options, or the recipe's defaults, may have changed since), or
    at another batch than its own."""
    if state is None:
        return []
    notes, batch = [], state["config"]["batch_size"]
    if differ := [n for n in NETWORK if getattr(asked, n) != getattr(cfg, n)]:
        said = " ".join(a for n in differ for a in option_argv(n, getattr(cfg, n)))
        notes.append(f"resuming from {found}: its network goes on as it was trained ({said})")
    if batch != cfg.batch_size:
        notes.append(
            f"resuming at batch {cfg.batch_size}; {found} trained at {batch} "
            f"(--batch-size {batch} goes on as it was)"
        )
    return notes


def _start_notes(cfg: TrainConfig, t: Trainee, catalog: Catalog, init, found, was) -> list[str]:
    """The lines a run prints as it starts on what it does differently from a plain run."""
    notes = []
    if t.screen_uv is None:
        notes.append(
            f"{catalog.urls[0]} has no screen UV layout: the checkpoints will render stored "
            "materials only (farm screen-uv STORE adds it; resume to carry it)"
        )
    if cfg.init is not None:
        notes.append(
            f"fine-tuning the network of {cfg.init}" if init is not None
            else f"resuming from {found}: --init {cfg.init} only starts a run"
        )  # fmt: skip
    if catalog.repeated:
        notes.append(
            f"{catalog.repeated} material(s) are in more than one store (by source_id): each "
            "is on one side of the split in all of them (farm jobs with another --seed render "
            "new materials)"
        )
    if note := _schedule_note(cfg, t, was):
        notes.append(note)
    if t.ema is not None:
        notes.append(
            f"weights averaged (decay {cfg.ema_decay}): the checkpoints render with the "
            "average, and the held-out scores measure it and the trained weights"
        )
    return notes


def _schedule_note(cfg: TrainConfig, t: Trainee, was: dict | None) -> str | None:
    """A line on a resumed cosine that does not go on as it was: it starts, or it goes on
    over another length."""
    if cfg.lr_schedule not in DECAYING or was is None or t.knee == tuple(was["knee"]):
        return None
    start, scale = t.knee
    how = (
        f"the run is {t.run_steps} steps long, not {was['total']}: the cosine rate goes on"
        if was["schedule"] in DECAYING
        else "the cosine rate starts"
    )
    return f"{how} from {cfg.lr * scale:.3g} at step {start} to 0 at step {t.run_steps}"


def _epoch(cfg: TrainConfig, rk: Rank, t: Trainee, batches, split_size: int, log, bar) -> int:
    """Train on ``batches`` (the rest of ``t.epoch``, or up to ``cfg.max_steps``) of a
    training split of ``split_size`` samples, logging every step and checkpointing on
    schedule; the number of images this rank trained on."""
    out, images = Path(cfg.out), 0
    join = t.net.join() if rk.distributed else contextlib.nullcontext()
    with join:
        for batch, waited in _timed(batches):
            if batch["epoch"] != t.epoch:
                raise LoaderError(
                    f"the data loader is out of step (a batch of epoch {batch['epoch'] + 1} "
                    f"in epoch {t.epoch + 1}): a worker lost batches ({WORKER_ERROR})"
                )
            loss = train_step(cfg, rk, t, batch)
            if t.ema is not None:
                t.ema.update(t.model)
            t.step += 1
            t.position = min(t.position + rk.world * cfg.batch_size, split_size)
            images += len(batch["id"])
            log.record(t, batch, loss, waited, bar)
            if t.step % cfg.log_every == 0:
                check_finite(t, out)
                log.flush(t, bar)
            if cfg.val_every and t.step % cfg.val_every == 0:
                log.validate(t, bar)
            if t.step % cfg.checkpoint_every == 0 or _new_best(t, log):
                save(cfg, rk, t, out, log)
            _check_time(rk, t, epoch_end=False)
            if _stopped(cfg, t):
                break
        if log.window["n"]:  # the steps since the last log line: every step is logged
            log.flush(t, bar)
    return images


def _at_max_steps(cfg: TrainConfig, t: Trainee) -> bool:
    return cfg.max_steps is not None and t.step >= cfg.max_steps


def _stopped(cfg: TrainConfig, t: Trainee) -> bool:
    """The run stops here: at ``--max-steps``, or past ``--time-limit``."""
    return t.timed_out or _at_max_steps(cfg, t)


def _check_time(rk: Rank, t: Trainee, epoch_end: bool) -> None:
    """Set ``t.timed_out`` once ``--time-limit`` has passed: after any step on one process;
    under torchrun only at an epoch's end, where every rank is (its ranks may have one batch
    more or less mid-epoch), and for all ranks at once if any rank's time is up."""
    if t.deadline is None or t.timed_out or (rk.distributed and not epoch_end):
        return
    over = time.monotonic() >= t.deadline
    if rk.distributed:
        flag = torch.tensor([float(over)], device=rk.device)
        dist.all_reduce(flag, op=dist.ReduceOp.MAX)
        over = bool(flag.item())
    t.timed_out = over


def _timed(batches):
    """``(batch, seconds waited for it)`` from an iterator of batches."""
    t0 = time.perf_counter()
    for batch in batches:
        yield batch, time.perf_counter() - t0
        t0 = time.perf_counter()


def _resume_state(cfg: TrainConfig, out: Path) -> tuple[dict | None, Path | None]:
    """The checkpoint to resume from (``None``: from scratch) and its path."""
    if not cfg.store:
        raise RunError("no store given: pass --store PATH (repeat for several)")
    found = checkpoint.latest(out)
    if found is not None and not cfg.resume:
        raise RunError(f"{out} already holds checkpoints: pass --resume, or another --out")
    state = checkpoint.load(found) if (cfg.resume and found is not None) else None
    if state is not None and "slim" in state:
        raise RunError(
            f"{found}: a slimmed checkpoint (trainer slim) has no optimizer state to resume "
            "from; start a new run from it with --init"
        )
    if state is not None:
        _check_schedule(cfg, state, found)
    return state, found


def _check_schedule(cfg: TrainConfig, state: dict, found: Path) -> None:
    """Refuse to train on past the end of a cosine rate, where every step would be at rate
    0. (A resume that asks for no more steps, or changes the schedule, is let through.)"""
    was = state.get("schedule")
    if not was or was["schedule"] not in DECAYING or cfg.lr_schedule not in DECAYING:
        return
    more = state["epoch"] < cfg.epochs and (cfg.max_steps is None or state["step"] < cfg.max_steps)
    if more and state["step"] >= was["total"]:
        raise RunError(
            f"{found} ended its cosine rate at step {was['total']}: more steps would train at "
            "rate 0; resume with --lr-schedule constant (and a small --lr) to train on"
        )


def _catalog(cfg: TrainConfig, rk: Rank, state: dict | None, found, init=None) -> Catalog:
    """The resumed run's catalog (checked against ``cfg``), or one snapshot of the stores
    taken by rank 0 and shared with every rank (even if a farm is still writing them), which
    keeps the split of the run ``init`` starts from (:mod:`trainer.training.finetune`)."""
    if state is not None:
        catalog = Catalog.from_dict(state["catalog"])
        if list(cfg.store) != [absolute_store(u) for u in catalog.urls]:
            raise RunError(f"{found} trained on {catalog.urls}, not {list(cfg.store)}")
        _check_resumed(cfg, state["config"], found)
    else:
        snap = [None]
        if rk.master:
            snap[0] = Catalog.snapshot(
                list(cfg.store), cfg.holdout_seed, cfg.holdout_fraction, None,
                keep=_kept(cfg, init),
            )  # fmt: skip
        if rk.distributed:
            dist.broadcast_object_list(snap, src=0)
        catalog = snap[0]
    if why := untrainable(catalog.resolution, nearest=False):
        raise RunError(f"{catalog.urls[0]}: {why}")
    if init is not None and (why := finetune.mismatch(init, cfg.init, catalog)):
        raise RunError(why)
    return catalog


def _kept(cfg: TrainConfig, init: dict | None):
    """The split a fine-tuned run keeps (:mod:`trainer.training.finetune`), or none, said, when the
    first run's stores cannot be read."""
    try:
        return finetune.kept_materials(init)
    except StoreError as exc:
        print(
            f"{cfg.init}: its stores cannot be read ({exc}): the held-out materials are drawn "
            "afresh and may include some it trained on",
            flush=True,
        )
        return None


def _check_resumed(cfg: TrainConfig, was: dict, found) -> None:
    """Refuse to resume with another epoch order (``--seed``, ``--shuffle-buffer``) or
    held-out draw (``--holdout-fraction``, ``--holdout-seed``) than the run's: the resumed
    run keeps its own. A checkpoint whose config has no ``holdout_seed`` drew its held-out
    materials with ``--seed``."""
    was = {"holdout_seed": was["seed"], **was}
    for name in ("seed", "shuffle_buffer", "holdout_fraction", "holdout_seed"):
        if was[name] != getattr(cfg, name):
            raise RunError(
                f"{found} was trained with --{name.replace('_', '-')} {was[name]}, "
                f"not {getattr(cfg, name)}"
            )


def _build(
    cfg: TrainConfig, rk: Rank, catalog: Catalog, state: dict | None, vgg, init=None
) -> Trainee:
    """Model, loss and optimizer: fresh (seeded), loaded from ``state``, or a fresh optimizer
    on the network of ``init``."""
    model_cfg = network_config(cfg, catalog.resolution)
    tonemap = Tonemap(exposure=cfg.exposure)
    geometry = None
    if (loaded := state if state is not None else init) is not None:
        model_cfg = ModelConfig(**loaded["model_config"])
        tonemap = Tonemap.from_dict(loaded["tonemap"])
    else:  # a fresh network takes the scene's buffers from the store
        geometry = _geometry(cfg, catalog)
    torch.manual_seed(cfg.seed)
    model = build_model(model_cfg, geometry).to(rk.device, memory_format=rk.fmt)
    criterion = RendererLoss(vgg, cfg.perceptual_weight, mixed_term(cfg.loss))
    criterion = criterion.to(rk.device, memory_format=rk.fmt)
    if rk.cuda:
        torch.backends.cudnn.benchmark = True  # fixed shapes: let cuDNN pick its fastest convs
    opt = torch.optim.Adam(
        model.parameters(), lr=cfg.lr, betas=(cfg.beta1, cfg.beta2),
        weight_decay=cfg.weight_decay, decoupled_weight_decay=True,
    )  # fmt: skip
    bad = torch.zeros((), dtype=torch.bool, device=rk.device)
    t = Trainee(model, model, opt, criterion, model_cfg, tonemap, catalog, bad)
    if rk.master:
        t.screen_uv = _screen_uv(catalog, state, init)
    if init is not None:
        model.load_state_dict(checkpoint.weights(init))
    if state is not None:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])  # train_step sets the rate: --lr may change
        for group in opt.param_groups:  # and the decay is this run's
            group["weight_decay"] = cfg.weight_decay
        t.step, t.epoch, t.position = state["step"], state["epoch"], state["position"]
        t.best = state.get("best")
    if rk.master and cfg.ema_decay > 0:  # from the weights as they are, or as it was kept
        t.ema = WeightAverage(model, cfg.ema_decay)
        if state is not None and state.get("ema") is not None:
            t.ema.load_state_dict(state["ema"])
    if rk.distributed:
        # the scene's buffers are constants: not broadcast every step as BatchNorm's are
        constants = [name for name, _ in model.named_buffers() if name.startswith("scene.")]
        DDP._set_params_and_buffers_to_ignore_for_model(model, constants)
        t.net = DDP(model, device_ids=[rk.device.index] if rk.cuda else None)
    return t


def network_config(cfg: TrainConfig, resolution: int) -> ModelConfig:
    """The network ``cfg`` asks for at ``resolution``."""
    return ModelConfig(
        resolution, cfg.width, cfg.skips, cfg.roughness_channels, arch=cfg.model,
        inputs=cfg.inputs, norm=cfg.norm, head=cfg.head, residual=cfg.residual,
        decoder_convs=cfg.decoder_convs, exposure=cfg.exposure,
    )  # fmt: skip


def _geometry(cfg: TrainConfig, catalog: Catalog):
    """The scene's geometry buffers from the first store, when the network's cues need
    them (``None`` when they do not); raises :class:`RunError` when the store has none."""
    try:
        model_cfg = network_config(cfg, catalog.resolution)
    except ValueError as exc:
        raise RunError(str(exc)) from None
    if not model_cfg.needs_geometry:
        return None
    url = catalog.urls[0]
    layout = Store(url).screen_uv()
    if layout is None or layout.geometry is None:
        what = "no screen UV layout" if layout is None else "a layout without geometry buffers"
        raise RunError(
            f"{url} has {what}, which --inputs {','.join(cfg.inputs)} needs: farm "
            "screen-uv STORE renders them (or train with --inputs light, or --recipe paper)"
        )
    return layout.geometry


def _screen_uv(catalog: Catalog, state: dict | None, init: dict | None = None) -> bytes | None:
    """The layout a checkpoint carries: the resumed checkpoint's, else the first store's
    (checked against that store), else the fine-tuned checkpoint's, else none."""
    if state is not None and state.get("screen_uv") is not None:
        return state["screen_uv"]
    store = Store(catalog.urls[0])
    if store.screen_uv() is None:  # raises StoreError when it is unusable
        return None if init is None else init.get("screen_uv")
    return store.backend.get(SCREEN_UV_FILE)


#: the most bytes (fp32) the scene cues of a preloaded split may take; a split whose cues would
#: take more has them computed in every step
PRELOAD_CUES_BYTES = 4 << 30


def preload_derive(t: Trainee, samples: int):
    """What ``--preload`` keeps of each of ``samples`` samples, computed once
    (:class:`Preloaded`'s ``derive``): the light, the tonemapped target, and the network's
    scene cues in place of the maps (where they fit in :data:`PRELOAD_CUES_BYTES`; the maps
    otherwise). Neither the target nor the cues depend on the weights and no sample is
    augmented, so a step reads them rather than computes them again: about a third of the
    default's operations a step (each a kernel launch on a GPU)."""
    scene = getattr(t.model, "scene", None)
    if scene is not None:
        cfg = t.model_cfg
        size = samples * cfg.network_channels * cfg.resolution**2 * 4
        scene = scene if size <= PRELOAD_CUES_BYTES else None

    @torch.no_grad()
    def derive(data: dict) -> dict:
        kept = {"light": data["light"], "target": t.tonemap(data["render"])}
        if scene is None:
            return kept | {"maps": data["maps"]}
        x = model_inputs(data["maps"], t.model_cfg.roughness_channels)
        return kept | {"cues": scene(x, data["light"])}

    return derive


def train_step(cfg: TrainConfig, rk: Rank, t: Trainee, batch: dict) -> torch.Tensor:
    """One optimizer step on ``batch``; returns the loss (a detached tensor, not synced).

    A preloaded split's batch (:func:`preload_derive`) brings its target, and its scene cues
    in place of the maps. Under bf16 autocast (``rk.autocast``) the U-Net and VGG run in
    bf16, the L1, feature MSE, MS-SSIM and FLIP in fp32. A NaN or infinite gradient norm is
    raised as :class:`TrainingDiverged` at the next check."""
    light = batch["light"].to(rk.device, non_blocking=True)
    cues, x = batch.get("cues"), None
    if cues is None:
        maps = batch["maps"].to(rk.device, non_blocking=True)
        x = model_inputs(maps, t.model_cfg.roughness_channels).contiguous(memory_format=rk.fmt)
    if "target" in batch:
        target = batch["target"]
    else:
        target = t.tonemap(batch["render"].to(rk.device, non_blocking=True))
    with rk.autocasting():
        out = t.net(x, light) if cues is None else t.net(x, light, cues)
        loss = t.criterion(out, target)
    t.opt.zero_grad(set_to_none=True)
    loss.backward()
    rate = lr_at(t.step, cfg.lr, cfg.lr_schedule, t.run_steps, cfg.warmup_steps, t.knee)
    for group in t.opt.param_groups:
        group["lr"] = rate
    params = t.model.parameters()
    if cfg.clip > 0:
        norm = torch.nn.utils.clip_grad_norm_(params, cfg.clip)
    else:
        norm = torch.stack([p.grad.norm() for p in params]).norm()
    t.bad |= ~torch.isfinite(norm)
    t.opt.step()
    return loss.detach()


def check_finite(t: Trainee, out: Path, weights: bool = False) -> None:
    """Raise :class:`TrainingDiverged` if a gradient norm (or, with ``weights``, a weight) has
    been NaN or infinite. Reading ``bad`` syncs with the GPU, so it runs only at log and
    checkpoint steps; the value is identical on every rank (gradients are all-reduced)."""
    if weights and not all(torch.isfinite(p).all() for p in t.model.parameters()):
        t.bad.fill_(True)
    if t.bad.item():
        last = checkpoint.latest(out)
        raise TrainingDiverged(
            f"the loss or gradients became NaN/Inf by step {t.step}; stopped. "
            f"Last good checkpoint: {last or 'none'} (lower --lr or resume from it)"
        )


def epoch_end_saves(cfg: TrainConfig, t: Trainee, log: RunLog) -> bool:
    """Whether the end of an epoch writes a checkpoint: always at the run's end (its last
    epoch, ``--max-steps``, ``--time-limit``) and for a new best score; otherwise at every
    epoch's end, or with ``--checkpoint-seconds`` once that long has passed since the last
    checkpoint (the run's start before the first)."""
    if not cfg.checkpoint_seconds or t.epoch >= cfg.epochs or _stopped(cfg, t):
        return True
    return _new_best(t, log) or time.monotonic() - log.saved_at >= cfg.checkpoint_seconds


def _new_best(t: Trainee, log: RunLog) -> bool:
    """Whether the network was just scored (rank 0), better than ever before."""
    val = log.last_val
    return (
        val is not None
        and val["step"] == t.step
        and (t.best is None or val["psnr"] > t.best["psnr"])
    )


def save(cfg: TrainConfig, rk: Rank, t: Trainee, out: Path, log: RunLog) -> None:
    """Rank 0 writes a checkpoint, after every rank has checked the weights are finite; it is
    also ``checkpoints/best.pt`` when the network was just scored, better than ever before
    (a mid-epoch score that is writes a checkpoint of its own: :func:`_epoch`)."""
    check_finite(t, out, weights=True)
    log.saved_at = time.monotonic()
    if not rk.master:
        return
    better = _new_best(t, log)
    if better:
        t.best = {"step": t.step, "psnr": log.last_val["psnr"]}
    log.last_checkpoint = checkpoint.save(
        out,
        {
            "model": t.model.state_dict(),
            "optimizer": t.opt.state_dict(),
            "step": t.step,
            "epoch": t.epoch,
            "position": t.position,
            "config": cfg.to_dict(),
            "precision": rk.precision,  # what --precision auto resolved to on this device
            "model_config": t.model_cfg.to_dict(),
            "tonemap": t.tonemap.to_dict(),
            "catalog": t.catalog.to_dict(),
            **({"screen_uv": t.screen_uv} if t.screen_uv is not None else {}),
            **({"ema": t.ema.state_dict()} if t.ema is not None else {}),
            "best": t.best,
            "schedule": record(cfg.lr_schedule, t.run_steps, t.knee),
        },
        keep=cfg.keep,
    )
    if better:
        checkpoint.keep_best(log.last_checkpoint)
