"""``farm``: the render farm's command line (thin over ``render_jobs`` and, later, the farm)."""

from __future__ import annotations

import sys
from pathlib import Path

import click
from tqdm import tqdm

from render_jobs.errors import MaterialError, RenderError
from render_jobs.specs import DEVICES, RenderSettings


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """shaderball render farm: ground-truth shaderball renders with Blender Cycles."""


@main.command()
@click.option(
    "--material",
    "-m",
    required=True,
    metavar="uniform|procedural|PATH",
    help="A random uniform or procedural material, a 5-panel SVBRDF PNG, or a per-map folder.",
)
@click.option("--out", "-o", required=True, type=click.Path(path_type=Path), help="Output folder.")
@click.option(
    "--suns",
    default=5,
    show_default=True,
    type=click.IntRange(1, 64),
    help="Random suns (direction + turbidity) to render.",
)
@click.option(
    "--resolution",
    default=400,
    show_default=True,
    type=click.IntRange(8, 8192),
    help="Image side in pixels.",
)
@click.option(
    "--samples",
    default=150,
    show_default=True,
    type=click.IntRange(1),
    help="Cycles samples per pixel.",
)
@click.option(
    "--seed",
    default=0,
    show_default=True,
    type=click.IntRange(0),
    help="Seed of the material draw, suns and Cycles.",
)
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
    """
    from render_jobs.preview import prepare, render_preview

    settings = RenderSettings(
        resolution=resolution, samples=samples, threads=threads, device=device
    )
    try:
        spec, maps = prepare(material, seed)  # validate before anything renders
    except MaterialError as exc:
        raise click.ClickException(str(exc)) from None
    bar = tqdm(total=suns, desc="rendering", unit="frame", file=sys.stderr)
    try:
        result = render_preview(
            spec,
            maps,
            out,
            settings,
            suns=suns,
            seed=seed,
            on_progress=lambda k: bar.update(k - bar.n),
        )
    except (MaterialError, RenderError) as exc:
        bar.close()
        raise click.ClickException(str(exc)) from None
    bar.close()
    times = [r.seconds for r in result.result.renders]
    click.echo(f"material  {result.spec.source_id}")
    total = sum(times)
    click.echo(f"frames    {len(times)} in {total:.1f} s ({total / len(times):.2f} s each)")
    click.echo(f"wrote     {result.out}/contact_sheet.png (and EXR/PNG per map and sun)")


if __name__ == "__main__":
    main()
