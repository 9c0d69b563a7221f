"""The per-rank training loop (``trainer train``), top to bottom in one file.

One process trains on CPU or one GPU. Under torchrun (``trainer launch``) every rank runs this
same loop as one DDP job: NCCL on GPUs, gloo on CPU. Examples::

    trainer train --store out/demo.zarr --epochs 1 --loss l1 --out runs/demo      # one process
    trainer launch --store out/demo.zarr --epochs 1 --loss l1 --out runs/demo     # torchrun
    trainer launch --nodes 2 --nproc-per-node 8 --rdzv-endpoint head:29400 ...    # 2 nodes x 8

On CUDA: bf16 autocast and channels_last (the U-Net and VGG16), cudnn.benchmark. Each rank
reads its own disjoint part of every epoch (``trainer.data``); ranks that end an epoch one
batch short are handled by DDP's ``join``.
Rank 0 writes the progress bar, ``RUNDIR/log.jsonl``, TensorBoard events under ``RUNDIR/tb``
and the checkpoints (``trainer.checkpoint``). A NaN or infinite gradient norm (identical on
every rank, since gradients are all-reduced) stops the run with :class:`TrainingDiverged`
before any checkpoint is written from the diverged weights.
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import os
import time
from pathlib import Path

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel as DDP
from torch.utils.data import DataLoader
from tqdm import tqdm

from trainer import checkpoint
from trainer.config import TrainConfig
from trainer.data import Catalog, ShardStream, steps_left
from trainer.model import ModelConfig, NeuralRenderer
from trainer.perceptual import RendererLoss, load_vgg
from trainer.targets import Tonemap, model_inputs

#: test hook: rank 0 of a first torchrun attempt exits abruptly after this global step
CRASH_AT = int(os.environ.get("SHADERBALL_TRAIN_CRASH_AT", "0")) or None


def _first_attempt() -> bool:
    return os.environ.get("TORCHELASTIC_RESTART_COUNT") == "0"


class TrainingDiverged(RuntimeError):
    """The loss or gradients became NaN or infinite."""


class RunError(ValueError):
    """The run cannot start as asked (run folder, stores, resolution)."""


def train(cfg: TrainConfig) -> dict:
    """Train as ``cfg`` says; returns rank 0's summary (steps, images, seconds, checkpoint)."""
    # ---- distribution and device ------------------------------------------------------------
    distributed = "RANK" in os.environ and "WORLD_SIZE" in os.environ
    rank = int(os.environ.get("RANK", 0))
    world = int(os.environ.get("WORLD_SIZE", 1))
    local_rank = int(os.environ.get("LOCAL_RANK", 0))
    use_cuda = cfg.device == "cuda" or (cfg.device == "auto" and torch.cuda.is_available())
    if use_cuda:
        torch.cuda.set_device(local_rank)
        device = torch.device("cuda", local_rank)
    else:
        device = torch.device("cpu")
    if distributed:
        _init_process_group("nccl" if use_cuda else "gloo", rank, world)
    master = rank == 0
    out = Path(cfg.out)

    try:
        return _train(cfg, rank, world, device, distributed, master, out)
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


def _train(cfg, rank, world, device, distributed, master, out) -> dict:
    # ---- what to train on, from scratch or from the latest checkpoint ----------------------
    if not cfg.store:
        raise RunError("no store given: pass --store PATH (repeat for several)")
    found = checkpoint.latest(out)
    if found is not None and not cfg.resume:
        raise RunError(f"{out} already holds checkpoints: pass --resume, or another --out")
    state = checkpoint.load(found) if (cfg.resume and found is not None) else None
    vgg = load_vgg(cfg.vgg_weights) if cfg.loss == "l1+vgg" else None  # fail before any work
    if state is not None:
        catalog = Catalog.from_dict(state["catalog"])
        if [str(Path(u)) for u in cfg.store] != [str(Path(u)) for u in catalog.urls]:
            raise RunError(f"{found} trained on {catalog.urls}, not {list(cfg.store)}")
        for name in ("seed", "shuffle_buffer"):  # they fix the epoch order being resumed
            if state["config"][name] != getattr(cfg, name):
                raise RunError(
                    f"{found} was trained with --{name.replace('_', '-')} "
                    f"{state['config'][name]}, not {getattr(cfg, name)}"
                )
    else:
        snap = [None]
        if master:  # one snapshot for all ranks, even if a farm is still writing the store
            snap[0] = Catalog.snapshot(list(cfg.store), cfg.seed, cfg.holdout_fraction, None)
        if distributed:
            dist.broadcast_object_list(snap, src=0)
        catalog = snap[0]
    if catalog.resolution % 16:
        raise RunError(
            f"{catalog.urls[0]}: resolution {catalog.resolution} is not divisible by 16 "
            "(the U-Net halves it four times)"
        )
    model_cfg = ModelConfig(catalog.resolution, cfg.width, cfg.skips, cfg.roughness_channels)
    tonemap = Tonemap(exposure=cfg.exposure)
    if state is not None:
        model_cfg = ModelConfig(**state["model_config"])
        tonemap = Tonemap.from_dict(state["tonemap"])

    # ---- model, loss, optimizer -------------------------------------------------------------
    torch.manual_seed(cfg.seed)
    cuda = device.type == "cuda"
    fmt = torch.channels_last if cuda else torch.contiguous_format
    model = NeuralRenderer(model_cfg).to(device, memory_format=fmt)
    criterion = RendererLoss(vgg, cfg.perceptual_weight).to(device, memory_format=fmt)
    if cuda:
        torch.backends.cudnn.benchmark = True  # fixed shapes: let cuDNN pick its fastest convs
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, betas=(cfg.beta1, cfg.beta2))
    step, epoch, position = 0, 0, 0
    if state is not None:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        for group in opt.param_groups:  # a resume may lower the rate (e.g. after divergence)
            group["lr"] = cfg.lr
        step, epoch, position = state["step"], state["epoch"], state["position"]
    net = DDP(model, device_ids=[device.index] if cuda else None) if distributed else model
    autocast = torch.autocast("cuda", dtype=torch.bfloat16) if cuda else contextlib.nullcontext()

    # ---- data ---------------------------------------------------------------------------------
    split = catalog.split("train")
    stream = ShardStream(
        split, batch=cfg.batch_size, seed=cfg.seed, buffer=cfg.shuffle_buffer, world=world,
        rank=rank, epochs=cfg.epochs,
    )  # fmt: skip
    loader = DataLoader(
        stream,
        batch_size=None,
        num_workers=cfg.workers,
        pin_memory=cuda,
        prefetch_factor=4 if cfg.workers else None,
    )
    batches = None  # one iteration for the whole run: the workers read across epoch ends
    per_step = world * cfg.batch_size

    # ---- logs ---------------------------------------------------------------------------------
    writer = None
    samples_log = None
    if master:
        out.mkdir(parents=True, exist_ok=True)
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(out / "tb"))
        (out / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2) + "\n")
        print(
            f"training on {len(split)} samples (held-out materials: "
            f"{sum(map(len, catalog.heldout))}), {world} rank(s) x batch {cfg.batch_size} "
            f"on {device.type}, "
            f"{model_cfg.resolution}², loss {cfg.loss}; from step {step}",
            flush=True,
        )
    if cfg.log_samples:
        (out / "samples").mkdir(parents=True, exist_ok=True)
        samples_log = open(out / "samples" / f"rank-{rank}.txt", "a")  # noqa: SIM115

    def save() -> Path | None:
        """Rank 0 writes a checkpoint (after checking that the weights are still finite)."""
        check_finite(weights=True)
        if not master:
            return None
        return checkpoint.save(
            out,
            {
                "model": model.state_dict(),
                "optimizer": opt.state_dict(),
                "step": step,
                "epoch": epoch,
                "position": position,
                "config": cfg.to_dict(),
                "model_config": model_cfg.to_dict(),
                "tonemap": tonemap.to_dict(),
                "catalog": catalog.to_dict(),
            },
            keep=cfg.keep,
        )

    bad = torch.zeros((), dtype=torch.bool, device=device)

    def check_finite(weights: bool = False) -> None:
        if weights and not all(torch.isfinite(p).all() for p in model.parameters()):
            bad.fill_(True)
        if bad.item():
            last = checkpoint.latest(out)
            raise TrainingDiverged(
                f"the loss or gradients became NaN/Inf by step {step}; stopped. "
                f"Last good checkpoint: {last or 'none'} (lower --lr or resume from it)"
            )

    # ---- the loop -----------------------------------------------------------------------------
    started = time.perf_counter()
    images = 0
    last_ckpt = None
    done = cfg.max_steps is not None and step >= cfg.max_steps
    while epoch < cfg.epochs and not done:
        if batches is None:
            stream.set_position(epoch, position)
            batches = iter(loader)
        mine = len(stream.batches(epoch, position))  # this rank's; one fewer on some ranks
        total = steps_left(len(split), world, cfg.batch_size, position)
        bar = tqdm(total=total, desc=f"epoch {epoch + 1}/{cfg.epochs}", disable=not master)
        window = _new_window()
        join = net.join() if distributed else contextlib.nullcontext()
        with join, contextlib.closing(bar):  # the bar ends its line even on errors
            t_fetch = time.perf_counter()
            for batch in itertools.islice(batches, mine):
                waited = time.perf_counter() - t_fetch
                if batch["epoch"] != epoch:
                    raise RuntimeError(
                        f"the loader is out of step: epoch {batch['epoch']} in {epoch}"
                    )
                maps = batch["maps"].to(device, non_blocking=True)
                x = model_inputs(maps, model_cfg.roughness_channels).contiguous(memory_format=fmt)
                light = batch["light"].to(device, non_blocking=True)
                target = tonemap(batch["render"].to(device, non_blocking=True))
                with autocast:  # the U-Net and VGG in bf16; L1 and feature MSE in fp32
                    pred = net(x, light)
                    loss = criterion(pred, target)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                if cfg.clip > 0:
                    norm = torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.clip)
                else:
                    norm = torch.stack([p.grad.norm() for p in model.parameters()]).norm()
                bad |= ~torch.isfinite(norm)
                opt.step()

                n = len(batch["id"])
                step += 1
                position = min(position + per_step, len(split))
                images += n
                window["wait"] += waited
                window["images"] += n
                window["loss"] += loss.detach()
                window["n"] += 1
                if samples_log is not None:
                    ids = ",".join(str(int(i)) for i in batch["id"])
                    samples_log.write(f"{epoch} {step} {ids}\n")
                bar.update(1)
                if step == CRASH_AT and master and _first_attempt():
                    os._exit(3)  # fault injection for tests: rank 0 dies, torchrun restarts all
                if step % cfg.log_every == 0:
                    check_finite()
                    if master:
                        _log(out, writer, bar, step, epoch, window, world)
                    window = _new_window()
                if step % cfg.checkpoint_every == 0:
                    last_ckpt = save() or last_ckpt
                if cfg.max_steps is not None and step >= cfg.max_steps:
                    done = True
                    break
                t_fetch = time.perf_counter()
        if not done:
            epoch, position = epoch + 1, 0
        last_ckpt = save() or last_ckpt
    if samples_log is not None:  # for tests: every rank's parameters must be identical
        blob = b"".join(p.detach().cpu().numpy().tobytes() for p in model.parameters())
        samples_log.write(f"params {hashlib.sha256(blob).hexdigest()}\n")
        samples_log.close()
    seconds = time.perf_counter() - started
    summary = {
        "steps": step,
        "epoch": epoch,
        "images_this_rank": images,
        "seconds": round(seconds, 3),
        "images_per_second": round(images * world / seconds, 2) if seconds > 0 else None,
        "checkpoint": str(last_ckpt or checkpoint.latest(out) or ""),
    }
    if writer is not None:
        writer.close()
    return summary


def _new_window() -> dict:
    """Running totals between two log lines."""
    return {"t": time.perf_counter(), "wait": 0.0, "images": 0, "loss": 0.0, "n": 0}


def _log(out: Path, writer, bar, step: int, epoch: int, window: dict, world: int) -> None:
    """One log line (rank 0's loss; throughput over all ranks), TensorBoard and the bar."""
    dt = max(time.perf_counter() - window["t"], 1e-9)
    rec = {
        "step": step,
        "epoch": epoch,
        "loss": round(float(window["loss"]) / max(window["n"], 1), 6),
        "images_per_second": round(window["images"] * world / dt, 2),
        "data_wait": round(window["wait"] / dt, 4),
        "time": round(time.time(), 3),
    }
    with open(out / "log.jsonl", "a") as f:
        f.write(json.dumps(rec) + "\n")
    for k in ("loss", "images_per_second", "data_wait"):
        writer.add_scalar(f"train/{k}", rec[k], step)
    bar.set_postfix(
        loss=rec["loss"], img_s=rec["images_per_second"], wait=f"{rec['data_wait']:.0%}"
    )
