"""``trainer``: train, launch, evaluate and run the neural renderer (thin over the library)."""

from __future__ import annotations

import json
import os
import shlex
from pathlib import Path

import click
from tabulate import tabulate

from render_jobs.materials.sources import load_map_bytes, one_material
from render_jobs.specs import Sun
from render_jobs.sun import sun_sweep
from render_jobs.tonemap import to_uint8
from shaderball.cli import Commands, human_bytes
from shaderball.progress import bar as progress_bar
from shaderball.web import serve, server_options, token_for
from storage.backend import write_atomic
from storage.extras import require
from storage.image_files import check_picture_name, save_animation, save_image
from storage.reader import Store
from trainer import runfiles
from trainer.checkpoint import WEIGHTS
from trainer.intervals import MIN_MATERIALS, bracket
from trainer.rendering.viewer import MAX_UPLOAD_MB
from trainer.slim import DTYPES as SLIM_DTYPES
from trainer.slim import write_slim
from trainer.training import config as train_config


def _fail(exc: Exception):
    raise click.ClickException(str(exc)) from None


def _make_config(kwargs: dict):
    if kwargs.get("init") is not None:  # the network comes whole from the checkpoint
        ctx = click.get_current_context()
        for name in train_config.NETWORK:
            if ctx.get_parameter_source(name) is click.core.ParameterSource.COMMANDLINE:
                raise click.UsageError(
                    f"--{name.replace('_', '-')}: a run started from --init takes its network "
                    "(shape and exposure) from that checkpoint"
                )
    try:
        return train_config.TrainConfig(**kwargs)
    except ValueError as exc:
        _fail(exc)


#: the --checkpoint help of the commands that also run an exported model
CHECKPOINT_OR_MODEL = "a checkpoint file, a run folder, or an .onnx model trainer export wrote"

device_option = click.option(
    "--device",
    default="auto",
    show_default=True,
    type=click.Choice(["auto", "cuda", "cpu"]),
    help="where the network runs",
)

WEIGHTS_HELP = (
    "a run trained with --ema-decay keeps two sets: the moving average of its weights "
    "(auto picks it) and the optimizer's own (trained)"
)
weights_option = click.option(
    "--weights",
    default="auto",
    show_default=True,
    type=click.Choice(WEIGHTS),
    help=WEIGHTS_HELP,
)


@click.group(cls=Commands, context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Train and run the neural material renderer on shard stores made by `farm submit`.

    \b
      trainer launch --store out/demo.zarr --epochs 1 --out runs/demo
      trainer eval --checkpoint runs/demo
      trainer render --checkpoint runs/demo --store out/demo.zarr --sample 0 -o out.png
    """
    require("trainer", "torch")


@main.command()
@train_config.options
def train(**kwargs) -> None:
    """Train on one process: the per-rank entry that `trainer launch` runs under torchrun.

    Run it directly for a single CPU/GPU process. Examples:

    \b
      trainer train --store out/demo.zarr --epochs 1 --out runs/demo
      trainer train --store out/set.zarr --ema-decay 0.999 --out runs/ema  # averaged weights
    """
    from trainer.training.train import train

    cfg = _make_config(kwargs)
    if int(os.environ.get("TORCHELASTIC_RESTART_COUNT", "0")) > 0:
        cfg.resume = True  # torchrun restarted the ranks: continue from the last checkpoint
    summary = train(cfg)
    if int(os.environ.get("RANK", "0")) == 0:
        val, best = summary["val"], summary["best"]
        held = f"; held-out PSNR {val['psnr']:.2f} dB at step {val['step']}" if val else ""
        click.echo(
            f"done: {summary['steps']} steps, {summary['images_per_second']} images/s, "
            f"{summary['seconds']:.1f} s{held}; checkpoint {summary['checkpoint']}"
        )
        if summary["timed_out"]:
            click.echo(f"stopped by --time-limit {cfg.time_limit:g}: --resume goes on from here")
        if best:
            path = Path(cfg.out) / runfiles.CHECKPOINTS / runfiles.BEST
            click.echo(f"best:  {path} (step {best['step']}, held-out {best['psnr']:.2f} dB)")
        click.echo(f"evaluate: trainer eval --checkpoint {shlex.quote(cfg.out)}")


def _procs(ctx, param, value):
    """``--nproc-per-node``: a count, or ``auto`` (as Kubeflow may set it): all GPUs or 1."""
    if value is None or str(value).lower() in ("auto", "gpu", "cpu", ""):
        return None
    try:
        return int(value)
    except ValueError:
        raise click.BadParameter(f"{value!r} is not a number or 'auto'") from None


@main.command(context_settings={"show_default": True})
@click.option("--nodes", default=1, type=int, envvar="PET_NNODES", help="nodes in the job")
@click.option("--nproc-per-node", default=None, callback=_procs, envvar="PET_NPROC_PER_NODE",
              help="ranks per node, or auto [all GPUs, or 1 on CPU]")  # fmt: skip
@click.option("--rdzv-endpoint", default=None, help="HOST:PORT of the c10d rendezvous (nodes > 1)")
@click.option(
    "--master-addr",
    default=None,
    envvar="PET_MASTER_ADDR",
    help="host of node 0, for torchrun's static rendezvous (Kubeflow Trainer)",
)
@click.option("--master-port", default=29400, type=click.IntRange(1, 65535),
              envvar="PET_MASTER_PORT",
              help="port of the static rendezvous on --master-addr")  # fmt: skip
@click.option("--node-rank", type=int, default=None, envvar="PET_NODE_RANK",
              help="this node's rank in the static rendezvous (0 hosts it); c10d ranks "
              "the nodes itself")  # fmt: skip
@click.option("--max-restarts", default=0, type=click.IntRange(min=0),
              help="torchrun restarts of failed ranks")  # fmt: skip
@click.option("--dry-run", is_flag=True, help="print the torchrun command, do not run it")
@train_config.options
def launch(
    nodes, nproc_per_node, rdzv_endpoint, master_addr, master_port, node_rank, max_restarts,
    dry_run, **kwargs,
):  # fmt: skip
    """Train with torchrun: DDP over every rank of every node.

    With no launch options: one node, all its GPUs (or one CPU process). Example, the
    smallest run:

    \b
      trainer launch --store out/demo.zarr --epochs 1 --out runs/demo

    Two nodes with 8 GPUs each (the same command on both; it prints it):

    \b
      trainer launch --nodes 2 --nproc-per-node 8 --rdzv-endpoint node0:29400 \\
          --store s3://bucket/ds.zarr --out /shared/runs/r1

    Fine-tune a trained network on a new material library (the materials the first run
    held out stay held out):

    \b
      trainer launch --init runs/r1 --store out/set.zarr --store out/leather.zarr \\
          --lr 1e-4 --epochs 5 --out runs/r1-leather

    In a Kubeflow Trainer TrainJob (torch-distributed runtime) the node count, rank and
    rendezvous come from its PET_* variables: give only the training options.
    """
    from trainer.training.launch import (
        LaunchConfig,
        other_node_commands,
        run_torchrun,
        torchrun_argv,
    )
    from trainer.training.train import preflight

    cfg = _make_config(kwargs)
    try:
        lc = LaunchConfig(
            nodes, nproc_per_node, rdzv_endpoint, node_rank, max_restarts,
            master_addr=master_addr, master_port=master_port,
        )  # fmt: skip
    except ValueError as exc:
        _fail(exc)
    if not dry_run:  # bad input ends here, in one line, before any rank starts
        preflight(cfg, ranks=lc.procs())
    argv = torchrun_argv(lc, cfg)
    click.echo("torchrun: " + shlex.join(argv), err=True)
    others = other_node_commands(lc, cfg) if nodes > 1 else []
    where = "on another node" if master_addr else "on each other node"
    for line in others:
        click.echo(f"{where}: {line}", err=True)
    if dry_run:
        return
    run_torchrun(argv)


@main.command("eval")
@click.option(
    "--checkpoint",
    "ckpts",
    required=True,
    multiple=True,
    help=f"{CHECKPOINT_OR_MODEL} (repeat to compare several on the same samples)",
)
@click.option("--store", "stores", multiple=True, help="the run's stores at another address")
@click.option("--batch-size", default=8, show_default=True, type=click.IntRange(min=1),
              help="images per batch")  # fmt: skip
@click.option("--grid", type=click.Path(path_type=Path), default=None,
              help="the grid picture (.png, .jpg, .webp) [RUN/eval.png for one run]")  # fmt: skip
@click.option("--grid-count", default=4, show_default=True, type=click.IntRange(min=0),
              help="samples in the grid (0: no grid)")  # fmt: skip
@click.option(
    "--on",
    "on",
    multiple=True,
    metavar="STORE",
    help="evaluate on every sample of this store of other materials (repeatable) instead of "
    "the run's held-out split",
)
@device_option
@click.option(
    "--weights",
    multiple=True,
    type=click.Choice(WEIGHTS),
    help=f"{WEIGHTS_HELP}; once for every --checkpoint, or once per --checkpoint in order  "
    "[default: auto]",
)
@click.option(
    "--per-sample",
    type=click.Path(path_type=Path),
    default=None,
    help="a .csv file of every sample's scores, with its material and sun, for each checkpoint",
)
@click.option(
    "--trained",
    is_flag=True,
    help="score one run's training materials instead of its held-out ones: how well it fits "
    "what it saw, beside its held-out score (the difference is how much it overfits)",
)
@click.option("--json", "as_json", is_flag=True, help="print the metrics as JSON")
def eval_(
    ckpts, stores, batch_size, grid, grid_count, on, device, weights, per_sample, trained, as_json
):
    """PSNR, SSIM and FLIP on held-out materials, overall and per kind, and a PNG grid
    (ground truth | prediction | error x4) of a few samples.

    The held-out materials are the run's held-out split, or, with --on, every material of
    stores the run never trained on (e.g. the same sources rendered with another --seed).
    An .onnx model from trainer export is scored in ONNX Runtime on the same materials (the
    file names its run's stores and held-out split): what a tool running that file shows.

    Several --checkpoint are scored on the same samples, each batch read once, and each
    after the first is compared with the first: the mean PSNR, SSIM and FLIP differences
    with 95 % intervals of a bootstrap over materials, and the share of samples where its
    PSNR is higher. They are scored on the first's held-out samples, which none of the others
    may have trained on: runs that hold out the same materials (the same --holdout-seed and
    --holdout-fraction), or a network and one fine-tuned from it (--init), either way round.
    With --on they are scored on those stores.

    \b
    Examples:
      trainer eval --checkpoint runs/demo --grid runs/demo/eval.png
      trainer eval --checkpoint runs/a --on out/test.zarr --json
      trainer eval --checkpoint runs/demo/ball.onnx --grid onnx-eval.png
      trainer eval --checkpoint runs/ema --weights trained    # without the run's average
      trainer eval --checkpoint runs/seed0 --checkpoint runs/seed1 --grid both.png
      trainer eval --checkpoint runs/ema --checkpoint runs/ema --weights trained --weights average
      trainer eval --checkpoint runs/a --per-sample runs/a/samples.csv   # which materials fail
      trainer eval --checkpoint runs/tuned --checkpoint runs/a   # what fine-tuning gained
      trainer eval --checkpoint runs/a --trained --grid-count 0   # its training materials
    """
    check_picture_name(grid, "--grid")
    if per_sample is not None and per_sample.suffix.lower() != ".csv":
        raise click.BadParameter(
            f"'{per_sample}' does not name a .csv file", param_hint="--per-sample"
        )
    if len(weights) not in (0, 1, len(ckpts)):
        raise click.BadParameter(
            f"given {len(weights)} times for {len(ckpts)} checkpoints: once for all of them, "
            "or once per --checkpoint in order",
            param_hint="--weights",
        )
    if trained and (on or len(ckpts) > 1):
        raise click.BadParameter(
            "scores one checkpoint on its own run's training materials: not with --on or "
            "several --checkpoint",
            param_hint="--trained",
        )
    weights = list(weights) * (len(ckpts) if len(weights) == 1 else 1) or ["auto"] * len(ckpts)
    args = (stores, batch_size, grid, grid_count, on, device, per_sample, as_json)
    if len(ckpts) > 1:
        _compare(list(ckpts), weights, *args)
        return
    _eval_one(ckpts[0], weights[0], *args, trained=trained)


def _eval_one(
    ckpt, weights, stores, batch_size, grid, grid_count, on, device, per_sample, as_json,
    trained=False,
):  # fmt: skip
    """One model's scores, kept beside its run when they are what the run renders (of its
    held-out materials)."""
    from trainer.rendering.evaluate import evaluate

    run_scores = Path(ckpt).is_dir() and not on and not trained and weights == "auto"
    if grid is None and run_scores:
        grid = Path(ckpt) / runfiles.EVAL_GRID
    result = evaluate(
        ckpt, list(stores) or None, batch_size, grid, grid_count, device,
        list(on) or None, weights, per_sample, trained,
    )  # fmt: skip
    if run_scores:  # beside the run's log, for the dashboard's runs page
        data = json.dumps(result, indent=1, default=str).encode()
        write_atomic(Path(ckpt) / runfiles.EVAL, lambda f: f.write(data))
    _warn_unchecked(ckpt, result)
    if as_json:
        click.echo(json.dumps(result, indent=2))
        return
    o = result["overall"]
    runtime = "" if result["runtime"] == "torch" else f" in {result['runtime']}"
    kept = " (the run's moving average)" if result["weights"] == "average" else ""
    click.echo(
        f"step {result['checkpoint_step']}{runtime}{kept}: {o['n']} "
        f"{'training' if trained else 'held-out'} samples of "
        f"{o['materials']} material{'s' if o['materials'] != 1 else ''}"
    )
    rows = [
        (
            kind,
            m["n"],
            m["materials"],
            m["psnr"],
            bracket(m["psnr_low"], m["psnr_high"]),
            m["ssim"],
            m["flip"],
        )
        for kind, m in [("all", o), *result["by_kind"].items()]
    ]
    head = ["kind", "n", "materials", "PSNR dB", "95 % interval", "SSIM", "FLIP (lower is better)"]
    click.echo(tabulate(rows, head, floatfmt=("", "", "", ".2f", "", ".4f", ".4f")))
    click.echo(
        "PSNR interval: a bootstrap over materials, as their suns are not independent "
        f"(none under {MIN_MATERIALS} materials)"
    )
    if "grid" in result:
        click.echo(f"grid: {result['grid']}")
    if "per_sample" in result:
        click.echo(f"each sample's scores: {result['per_sample']}")


def _warn_unchecked(ckpt, result: dict) -> None:
    if result["on_checked_against_run"] is False:
        click.echo(
            f"warning: {ckpt} names no stores of its run, so the --on stores were not checked "
            "for materials it trained on",
            err=True,
        )


def _compare(ckpts, weights, stores, batch_size, grid, grid_count, on, device, per_sample, as_json):
    """Several models' scores on the same samples, each against the first."""
    from trainer.rendering.compare import compare, report

    result = compare(
        ckpts, weights, list(stores) or None, batch_size, grid, grid_count, device,
        list(on) or None, per_sample,
    )  # fmt: skip
    for model in result["models"]:
        _warn_unchecked(model["checkpoint"], model)
    if as_json:
        click.echo(json.dumps(result, indent=2))
        return
    click.echo(report(result))


def _floats(text: str | None, n: int, name: str):
    if text is None:
        return None
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        msg = f"{text!r} is not {n} comma-separated numbers"
        raise click.BadParameter(msg, param_hint=name) from None
    if len(vals) != n:
        raise click.BadParameter(f"{text!r} has {len(vals)} values, not {n}", param_hint=name)
    return vals


def _light(sun: str | None, turbidity: float | None, default):
    """The :class:`Sun` of the options, each falling back to ``default``'s
    ``(direction, turbidity)``; a sun below the horizon or a turbidity outside [1, 10] is a
    usage error."""

    direction = _floats(sun, 3, "--sun") or default[0]
    t = default[1] if turbidity is None else turbidity
    norm = sum(c * c for c in direction) ** 0.5
    if norm == 0:
        raise click.BadParameter("the sun direction must not be 0,0,0", param_hint="--sun")
    try:
        return Sun(tuple(float(c) / norm for c in direction), float(t))
    except ValueError as exc:
        hint = "--turbidity" if "turbidity" in str(exc) else "--sun"
        raise click.BadParameter(str(exc), param_hint=hint) from None


#: the light of ``trainer render --material`` when none is given: from the front left, 40°
DEFAULT_LIGHT = ((-0.5, -0.6, 0.62), 3.0)


@main.command()
@click.option("--checkpoint", "ckpt", required=True, help=CHECKPOINT_OR_MODEL)
@click.option(
    "--material",
    default=None,
    help="any one material, mapped without Blender: uniform:seed=S, procedural:seed=S, "
    "uniform:diffuse=R,G,B;specular=R,G,B;roughness=X, a 5-panel PNG or a per-map folder",
)
@click.option(
    "--store",
    default=None,
    help="the store holding --sample; with --material, a store whose screen UV layout to "
    "use when the checkpoint carries none",
)
@click.option("--sample", type=int, default=None, help="sample index in --store")
@click.option("--sun", default=None, help="X,Y,Z sun direction, z up [the sample's, or front left]")
@click.option("--turbidity", type=float, default=None, help="sky turbidity [the sample's, or 3]")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True,
              help="the picture: .png, .jpg or .webp; with --sweep, the animation: .png "
              "(APNG), .gif or .webp")  # fmt: skip
@click.option("--sweep", type=click.IntRange(2, 720), default=None, metavar="N",
              help="N frames of the sun going once round the sky at its elevation, as an "
              "animation")  # fmt: skip
@click.option("--fps", type=click.FloatRange(1, 60), default=12.0, show_default=True,
              help="the --sweep animation's frames a second")  # fmt: skip
@device_option
def render(ckpt, material, store, sample, sun, turbidity, output, sweep, fps, device):
    """Render any material with the network, under any sun, without Blender.

    --material takes anything farm submit accepts for one material; its maps are UV-mapped
    onto the ball with the screen UV layout the checkpoint carries. --store with --sample
    renders a stored material (its own sun unless --sun / --turbidity say otherwise). An
    .onnx model from trainer export runs in ONNX Runtime with the layout beside it.
    --sweep turns the sun once round the sky: the material under every sun, as an animation.
    PNGs carry the checkpoint, the material and the light in their text chunks.

    \b
    Examples:
      trainer render --checkpoint runs/demo --material textures/leather.png \\
          --sun 0.3,-0.5,0.8 --turbidity 3 -o leather.png
      trainer render --checkpoint runs/demo -o red.png \\
          --material 'uniform:diffuse=#b03a2e;specular=0.04;roughness=0.3'
      trainer render --checkpoint runs/demo --store out/demo.zarr --sample 3 -o ball.png
      trainer render --checkpoint runs/demo --material textures/leather.png \\
          --sun 0.3,-0.5,0.5 --sweep 48 -o leather.webp     # the sun once round
      trainer render --checkpoint ball.onnx --material textures/leather.png -o l.png
    """
    from PIL import Image

    if (material is None) == (sample is None):
        raise click.UsageError("give --material, or --store with --sample")
    if sample is not None and store is None:
        raise click.UsageError("--sample needs --store")
    check_picture_name(output, "-o", animated=sweep is not None)
    r, packed, light = _render_inputs(ckpt, material, store, sample, sun, turbidity, device)
    text = {
        "shaderball:checkpoint": str(ckpt),
        "shaderball:material": json.dumps(
            {"source": material} if material else {"store": store, "sample": sample}
        ),
        "shaderball:light": json.dumps({**light.to_dict(), "sweep": sweep}),
        "Software": "shaderball trainer render",
    }
    try:
        if sweep is None:
            images = [r.render(packed, light.direction, light.turbidity)]
        else:
            images = _sweep(r, packed, light, sweep)
        pictures = [Image.fromarray(to_uint8(img)) for img in images]
    except ValueError as exc:  # maps that do not fit the network
        _fail(exc)
    if sweep is None:
        save_image(pictures[0], output, text)
    else:
        save_animation(pictures, output, fps, text)
    click.echo(f"wrote {output}")


def _render_inputs(ckpt, material, store, sample, sun, turbidity, device):
    """``(renderer, stored maps, Sun)`` of ``trainer render``'s options; bad input ends the
    command in one line."""
    from trainer.rendering.base import material_mapper
    from trainer.rendering.load import load_renderer
    from trainer.rendering.mapping import textures_from_bytes

    try:
        if material is not None:
            maps = load_map_bytes(one_material(material))  # the material first: cheap errors
            light = _light(sun, turbidity, DEFAULT_LIGHT)
            r = load_renderer(ckpt, device)
            packed = material_mapper(r, store)(textures_from_bytes(maps)).cpu().numpy()
        else:
            s = Store(store)
            packed = s.packed_maps(s.layout.material_of_sample(sample))
            light = _light(sun, turbidity, s.light(sample))
            r = load_renderer(ckpt, device)
    except (ValueError, IndexError) as exc:  # a sample or maps the network cannot take
        _fail(exc)
    return r, packed, light


def _sweep(renderer, packed, sun, n: int):
    """The frames of ``--sweep n``, with a progress bar (:mod:`shaderball.progress`)."""
    from trainer.rendering.base import render_under

    frames = render_under(renderer, packed, sun_sweep(sun, n))
    return progress_bar(frames, total=n, desc="rendering", unit="frame")


@main.command()
@click.option("--checkpoint", "ckpt", required=True, help="a checkpoint file or a run folder")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True,
              help="the .onnx file (its screen UV layout goes beside it)")  # fmt: skip
@click.option("--opset", type=click.IntRange(11, 18), default=18, show_default=True,
              help="the ONNX opset, for older importers (Unity Sentis 1.x: 15)")  # fmt: skip
@click.option("--no-catalog", is_flag=True,
              help="leave out the addresses of the run's stores and its held-out split (a "
              "file to share): trainer eval then scores it --on other stores only")  # fmt: skip
@weights_option
def export(ckpt, output, opset, no_catalog, weights):
    """Export the network as an ONNX model, to run it without Python or torch (ONNX Runtime
    in a tool, a game engine or a browser).

    The model takes stored maps (N, 11, R, R) uint8, the sun direction (N, 3) and the
    turbidity (N,), and gives the display-ready image (N, 3, R, R) in [0, 1]: everything
    `trainer render` does after the maps. It is checked against the checkpoint in ONNX
    Runtime before it is kept. The checkpoint's screen UV layout, which maps new materials
    to stored maps, is written beside it as NAME.screen_uv.npz. Its metadata names the
    run's stores and held-out materials, so that trainer eval can score the file (leave them
    out with --no-catalog). Details: docs/training.md.

    \b
    Examples:
      trainer export --checkpoint runs/demo -o runs/demo/ball.onnx
      trainer export --checkpoint runs/a/checkpoints/step-00004000.pt -o ball-4000.onnx
      trainer export --checkpoint runs/demo --opset 15 -o ball-15.onnx   # Unity Sentis 1.x
      trainer export --checkpoint runs/demo --no-catalog -o share/ball.onnx
    """
    require("trainer export", "onnx", "onnxscript", "onnxruntime")
    from trainer.rendering.export import export as export_onnx
    from trainer.rendering.infer import Renderer

    if output.suffix != ".onnx":
        raise click.BadParameter(f"{str(output)!r} does not end in .onnx", param_hint="-o")
    renderer = Renderer.from_checkpoint(ckpt, "cpu", weights)
    click.echo("exporting, then checking the model in ONNX Runtime ...", err=True)
    done = export_onnx(renderer, output, opset, catalog=not no_catalog)
    click.echo(
        f"wrote {done.model} ({done.bytes / 2**20:.1f} MiB, ONNX opset {done.opset}); ONNX Runtime "
        f"renders it within {done.max_difference:.1e} of the checkpoint"
    )
    if done.screen_uv is not None:
        click.echo(f"wrote {done.screen_uv} (the screen UV layout for new materials)")


@main.command(context_settings={"show_default": True})
@click.option("--checkpoint", "ckpt", required=True, help="a checkpoint file or a run folder")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True,
              help="the slimmed checkpoint, a .pt file")  # fmt: skip
@click.option("--dtype", type=click.Choice(SLIM_DTYPES), default=SLIM_DTYPES[0],
              help="what the network's parameters are kept in")  # fmt: skip
@weights_option
def slim(ckpt, output, dtype, weights):
    """Keep a checkpoint's network alone: the weights it renders with, in half precision,
    without the optimizer's state or a second set of weights (an eighth of a run's
    checkpoint, or less), to carry or share.

    trainer render, eval, viewer, export and train --init take the file as they take the
    whole checkpoint: the weights are copied back into the network's fp32 parameters, and the
    store addresses, held-out split, screen UV layout and tonemap stay. A run cannot resume
    from it. What float16 costs in PSNR: docs/training.md.

    \b
    Examples:
      trainer slim --checkpoint runs/demo -o share/demo.pt
      trainer eval --checkpoint runs/demo --checkpoint share/demo.pt   # the rounding, paired
      trainer slim --checkpoint runs/demo --weights trained --dtype float32 -o demo-trained.pt
    """
    if output.suffix != ".pt":
        raise click.BadParameter(f"{str(output)!r} does not end in .pt", param_hint="-o")
    done = write_slim(ckpt, output, weights, dtype)
    click.echo(
        f"wrote {done.path} ({human_bytes(done.bytes)}, {human_bytes(done.source_bytes)} "
        f"before): the {done.weights} weights of step {done.step:,} in {dtype}"
    )


@main.command()
@click.option("--checkpoint", "ckpt", required=True, help=CHECKPOINT_OR_MODEL)
@click.option("--store", "stores", multiple=True,
              help="a store whose materials fill the gallery (repeatable)")  # fmt: skip
@click.option("--materials", "folders", multiple=True, metavar="DIR",
              help="a folder of materials (5-panel PNGs, per-map folders)")  # fmt: skip
@click.option("--max-upload-mb", type=click.IntRange(min=1), default=MAX_UPLOAD_MB,
              show_default=True,
              help="an upload's files together, at most (the page's upload box)")  # fmt: skip
@click.option("--cuda-graph", is_flag=True,
              help="render each frame through the network compiled in bf16 and replayed as a "
              "CUDA graph: the fastest frames, after a compile at start (CUDA, a torch "
              "checkpoint; docs/benchmarks.md)")  # fmt: skip
@server_options(port=8267)
@device_option
def viewer(ckpt, stores, folders, max_upload_mb, cuda_graph, host, port, token, device):
    """Serve the material viewer: any material on the ball through the network, live.

    Pick a material from the gallery (a store's materials, a folder's), upload a 5-panel PNG
    or per-map images, or build a uniform one; tint and scale its maps; drag the sun on the
    hemisphere and set the turbidity. The page shows each frame's time (mapping, network,
    encoding); for a stored material under a stored sun it shows the Cycles ground truth and
    the error beside the network's image. Save the view as PNG (material and light in its
    metadata). No Blender: materials are mapped with the checkpoint's screen UV layout. An
    .onnx model from trainer export runs in ONNX Runtime, with the layout beside it.

    \b
    Examples:
      trainer viewer --checkpoint runs/demo --store out/demo.zarr   # http://127.0.0.1:8267
      trainer viewer --checkpoint runs/a --materials textures/ambientcg --device cuda
      trainer viewer --checkpoint runs/a --store out/demo.zarr --cuda-graph   # fastest on CUDA
      trainer viewer --checkpoint runs/a --host 0.0.0.0   # prints a token, needed by every request
      trainer viewer --checkpoint ball.onnx --store out/demo.zarr   # an exported model
    """
    require("trainer viewer", "aiohttp", "jinja2")
    from trainer.rendering.viewer.app import build, make_app

    if cuda_graph:
        _check_cuda_graph(device)
        click.echo("compiling the network into a CUDA graph (tens of seconds)", err=True)
    try:
        view, notes = build(
            ckpt, list(stores), list(folders), device, max_upload_mb << 20, cuda_graph
        )
    except ValueError as exc:  # a folder, store or upload limit the viewer cannot take
        _fail(exc)
    for line in notes:
        click.echo(line, err=True)
    token = token_for(host, token, echo=click.echo)
    serve(make_app(view, token), host, port, lambda line: click.echo(line, err=True), "viewer")


def _check_cuda_graph(device: str) -> None:
    """``--cuda-graph`` on a device that has no CUDA ends the command in one line."""
    from trainer.devices import pick_device

    where = pick_device(device).type
    if where != "cuda":
        _fail(ValueError(f"--cuda-graph needs a CUDA device, and the network would run on {where}"))


if __name__ == "__main__":
    main()
