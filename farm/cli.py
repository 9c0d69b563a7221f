"""``farm``: the render farm's command line (thin over ``farm`` and ``render_jobs``)."""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import click

from farm.cancel import request_cancel
from farm.driver import submit as run
from farm.materials import dry_run, format_dry_run
from farm.plan import RENDER_OPTIONS, JobConfig
from farm.plan import options as job_options
from farm.state import load_state
from farm.status import WORKER_ROWS, format_status
from render_jobs.preview import prepare, render_preview
from render_jobs.process import RenderProcess
from render_jobs.screen_uv import default_supersample
from render_jobs.specs import DEVICES, RenderSettings
from shaderball.cli import Commands
from shaderball.progress import bar as progress_bar
from shaderball.signals import exit_stopped, stop_on_sigterm
from shaderball.web import serve, server_options, token_for
from storage.backend import Backend
from storage.extras import require
from storage.reader import Store
from storage.writer import put_screen_uv


def _job_config(cls, **kwargs):
    """The job's config; a setting it refuses (``ValueError``) ends in one line."""
    try:
        return cls(**kwargs)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None


def _fixed_sun(text: str | None, turbidity: float):
    if text is None:
        return None
    try:
        x, y, z = (float(v) for v in text.split(","))
    except ValueError:
        raise click.BadParameter(f"{text!r} is not X,Y,Z", param_hint="--fixed-sun") from None
    return (x, y, z, turbidity)


#: --suns, --resolution, --samples, --seed: the options of every command that renders
render_options = functools.partial(job_options, names=RENDER_OPTIONS)


@click.group(cls=Commands, context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """shaderball render farm: ground-truth shaderball renders with Blender Cycles.

    \b
      farm submit -m uniform:4 -m procedural:4 --resolution 128 -o out/demo.zarr
      farm status out/demo.zarr --watch
      farm dashboard out
    """


@main.command()
@click.option(
    "--material",
    "-m",
    required=True,
    metavar="MATERIAL",
    help="One material: uniform or procedural (random), uniform:seed=S, procedural:seed=S, "
    "uniform:diffuse=R,G,B;specular=R,G,B;roughness=X, a 5-panel SVBRDF PNG or a per-map "
    "folder (any library's naming; `farm materials svbrdf:PATH` shows how it is read).",
)
@click.option("--out", "-o", required=True, type=click.Path(path_type=Path), help="Output folder.")
@render_options
@click.option(
    "--threads",
    default=0,
    show_default=True,
    type=click.IntRange(0),
    help="Cycles CPU threads (0 = all cores).",
)
@click.option(
    "--device",
    default="CPU",
    show_default=True,
    type=click.Choice(DEVICES),
    help="Cycles device (CUDA/OPTIX need a GPU).",
)
def preview(material, out, suns, resolution, samples, seed, threads, device) -> None:
    """Render one material under a few suns, locally (no Ray), and write pictures.

    Writes the screen-space maps and every sun's render as EXR (linear) and PNG
    (tonemapped), a labelled contact sheet and preview.json into OUT.

    \b
    Examples:
      farm preview --material procedural --out out/preview
      farm preview -m uniform --suns 3 --resolution 128 --samples 32 -o out/quick
      farm preview -m textures/leather.png -o out/leather
      farm preview -m 'uniform:diffuse=#b03a2e;specular=0.04;roughness=0.3' -o out/red
    """
    require("farm preview", "bpy")

    settings = RenderSettings(
        resolution=resolution, samples=samples, threads=threads, device=device
    )
    spec, maps = prepare(material, seed)  # validate before anything renders
    # made at the first report (0 frames, once the output folder took a file): an output
    # folder that cannot be written fails in one line, without a bar
    bar = None

    def progress(done: int) -> None:
        nonlocal bar
        bar = bar or progress_bar(total=suns, desc="rendering", unit="frame")
        bar.update(done - bar.n)

    stop_on_sigterm()  # the temporary folder goes on SIGTERM as on Ctrl-C
    try:
        try:
            result = render_preview(
                spec, maps, out, settings, suns=suns, seed=seed, on_progress=progress
            )
        finally:  # the bar's last line before any error's
            if bar is not None:
                bar.close()
    except KeyboardInterrupt:
        exit_stopped(f"nothing was written to {out}")
    times = [r.seconds for r in result.result.renders]
    click.echo(f"material  {result.spec.source_id}")
    total = sum(times)
    click.echo(f"frames    {len(times)} in {total:.1f} s ({total / len(times):.2f} s each)")
    click.echo(f"wrote     {result.out}/contact_sheet.png (and EXR/PNG per map and sun)")


@main.command()
@job_options
@click.option(
    "--fixed-sun",
    default=None,
    metavar="X,Y,Z",
    help="Render every material under this one sun direction (with --suns 1): a fixed-light "
    "dataset, for models without a light input.",
)
@click.option(
    "--fixed-turbidity",
    default=3.0,
    show_default=True,
    type=click.FloatRange(1, 10),
    help="The sky turbidity with --fixed-sun.",
)
def submit(out, fixed_sun, fixed_turbidity, **settings):
    """Render a dataset on Ray workers into a shard store; resumes an interrupted job.

    Plans every material x --suns suns (seeded by --seed), validates every material first,
    then renders on long-lived Blender workers and commits shards as they complete. Running
    the same command again resumes: committed shards are skipped. A different dataset setting
    for an existing store is refused.

    \b
    Examples:
      farm submit -m uniform:20 -m procedural:20 --resolution 128 --samples 32 -o out/small.zarr
      farm submit -m svbrdf:data/deschaintre -o s3://bucket/set.zarr --address ray://head:10001
      farm submit -m uniform:20 --samples 2 --denoise -o out/small-2spp-oidn.zarr  # a baseline
    """
    require("farm submit", "ray")

    try:
        cfg = _job_config(JobConfig, out=out, fixed_sun=_fixed_sun(fixed_sun, fixed_turbidity),
                          **settings)  # fmt: skip
        summary = run(cfg, echo=click.echo)
    except KeyboardInterrupt:
        exit_stopped(
            f"every committed shard is kept (farm status {out}), and the same command resumes"
        )
    _echo_summary(summary)


def _echo_summary(summary) -> None:
    """What a finished, cancelled or failed job did; a failed one exits 1."""
    rate = summary.frames_rendered / summary.wall_s if summary.wall_s else 0.0
    click.echo(
        f"frames    {summary.frames_rendered} rendered, {summary.frames_skipped} already "
        f"there, {summary.frames_total} in the dataset"
    )
    click.echo(
        f"time      {summary.wall_s:.1f} s ({rate:.2f} frames/s; start-up "
        f"{summary.startup_s:.1f} s)"
    )
    click.echo(f"store     {summary.store}   (inspect: shards info {summary.store})")
    if summary.cancelled:
        click.echo("cancelled: every whole shard is committed; run the same command to resume")
        return
    if summary.failed_attempts and summary.ok:
        click.echo(f"retried   {summary.failed_attempts} failed attempt(s), every material "
                   f"rendered on a retry (farm status {summary.store} lists them)")  # fmt: skip
    if not summary.ok:
        for m, err in sorted(summary.failed_materials.items()):
            click.echo(f"FAILED    material {m}: {err}", err=True)
        for shard, err in sorted(summary.failed_commits.items()):
            click.echo(f"FAILED    commit of shard {shard}: {err}", err=True)
        click.echo(
            f"{len(summary.failed_materials)} material(s) and {len(summary.failed_commits)} "
            f"commit(s) failed; shards {summary.failed_shards} are not committed. Run the same "
            "command to retry.",
            err=True,
        )
        sys.exit(1)


@main.command()
@click.argument("sources", nargs=-1, required=True, metavar="SOURCE...")
@click.option("--seed", default=0, show_default=True, help="Dataset seed (as farm submit).")
@click.option("--json", "as_json", is_flag=True, help="Print the dry run as JSON.")
def materials(sources, seed, as_json):
    """Dry run of --materials: every material found, without Ray or Blender.

    SOURCE is what farm submit -m takes: uniform:N, procedural:N or svbrdf:PATH (a 5-panel
    PNG, a per-map folder of any library's naming, or a folder of either). For each file
    material it prints the file used for each map (size, bit depth), the workflow
    (spec-gloss or metal-rough), the conversions applied and the files ignored; for each
    material that cannot be used, its one-line error. Exit 1 when any cannot be used.

    \b
    Examples:
      farm materials svbrdf:textures/ambientcg
      farm materials svbrdf:textures/polyhaven/brick_wall_001 --json
      farm materials uniform:10 svbrdf:data/deschaintre
    """

    def progress(items):
        return progress_bar(items, desc="reading", unit="material", leave=False)

    run = dry_run(list(sources), seed, progress=None if as_json else progress)
    click.echo(json.dumps(run.to_dict(), indent=1) if as_json else format_dry_run(run))
    if run.failed:
        sys.exit(1)


@main.command()
@click.argument("roots", nargs=-1, metavar="ROOT...")
@click.option("--runs", "run_dirs", multiple=True, metavar="DIR",
              help="A trainer run folder, or a folder of them (repeatable).")  # fmt: skip
@server_options(port=8266)
def dashboard(roots, run_dirs, host, port, token):
    """Serve the farm dashboard: jobs, shards, failures, workers, renders, runs, metrics.

    A ROOT is a store, a folder of stores or an s3:// prefix of stores (default: out).
    It reads only what farm submit and trainer write, so it shows running, finished and
    lost jobs, with or without Ray. /metrics is in the Prometheus text format.

    \b
    Examples:
      farm dashboard out --runs runs                  # http://127.0.0.1:8266
      farm dashboard s3://bucket/sets --host 0.0.0.0  # prints a token; needed by every request
    """
    require("farm dashboard", "aiohttp", "jinja2", "prometheus_client")
    from farm.dashboard.app import Dashboard, make_app

    token = token_for(host, token, echo=click.echo)
    roots = list(roots) or ["out"]
    for where in [*roots, *run_dirs]:  # a typo, or a folder the farm or trainer makes later
        if "://" not in where and not Path(where).exists():
            click.echo(f"warning: {where} does not exist (yet): shown once it is written", err=True)
    app = make_app(Dashboard(roots, list(run_dirs)), token)
    serve(app, host, port, lambda line: click.echo(line, err=True), "dashboard")


@main.command("screen-uv")
@click.argument("store")
@click.option(
    "--supersample",
    type=click.IntRange(1, 16),
    default=None,
    help="Sub-samples a pixel side [default: 4 up to 256², 3 at 400², 2 above].",
)
@click.option(
    "--threads", default=0, show_default=True, type=click.IntRange(0), help="Cycles threads."
)
def screen_uv(store, supersample, threads):
    """Render STORE's screen UV layout once and keep it with the store.

    The layout (what the camera sees of the shaderball's UVs, at sub-pixel resolution) lets
    the trainer turn any material's maps into the network's input without Blender
    (trainer render --material, trainer viewer). farm submit writes it with every new
    store; this command adds it to a store made before, or replaces it. Local Blender, no
    Ray; a few seconds.

    \b
    Example:
      farm screen-uv out/set.zarr
    """
    require("farm screen-uv", "bpy")

    s = Store(store)
    settings = RenderSettings(
        resolution=s.layout.resolution,
        samples=1,
        threads=threads,
        texture_tiling=s.settings.get("texture_tiling", 2.0),
    )
    factor = supersample or default_supersample(s.layout.resolution)
    with RenderProcess(settings) as worker:
        layout = worker.screen_uv(factor)
    put_screen_uv(s, layout)
    click.echo(f"wrote {store}/screen_uv.npz: {factor}x{factor} sub-samples a pixel")


@main.command()
@click.argument("store")
def cancel(store):
    """Ask the running job on STORE to stop.

    Its driver (within a few seconds) stops handing out tasks, lets the ones in flight
    finish, commits every whole shard, records the job as cancelled and exits 0. Nothing
    committed is lost; running the same farm submit again resumes.

    \b
    Example:
      farm cancel out/set.zarr
    """
    state = load_state(store)
    if state is None:
        raise click.ClickException(f"{store}: no farm job state (was it made by farm submit?)")
    if state["effective_status"] != "running":
        raise click.ClickException(f"{store}: the job is {state['effective_status']}, not running")
    request_cancel(Backend(store), by="farm cancel")
    click.echo(f"cancel requested: driver {state['driver']} stops within a few seconds")


@main.command()
@click.argument("store")
@click.option("--json", "as_json", is_flag=True, help="Print the job state as JSON.")
@click.option("--watch", is_flag=True, help="Refresh every 2 s until the job ends.")
@click.option(
    "--all-workers", is_flag=True, help="List every worker [default: the first 20, and a count]."
)
def status(store, as_json, watch, all_workers):
    """Show a farm job's progress, failures and workers, from the state kept with its store.

    \b
    Examples:
      farm status out/small.zarr
      farm status out/small.zarr --watch
      farm status s3://bucket/sets/paper-400.zarr --all-workers
    """
    import time

    while True:
        state = load_state(store)
        if state is None:
            raise click.ClickException(f"{store}: no farm job state (was it made by farm submit?)")
        if as_json:
            click.echo(json.dumps(state, indent=1))
        else:
            if watch:
                click.clear()
            click.echo(format_status(state, None if all_workers else WORKER_ROWS))
        if not watch or state["effective_status"] != "running":
            return
        time.sleep(2)


if __name__ == "__main__":
    main()
