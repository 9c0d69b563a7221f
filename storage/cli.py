"""``shards``: inspect shard stores (thin over ``storage``; errors are one line)."""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
from pathlib import Path

import click
from PIL import Image
from tabulate import tabulate

from render_jobs.contact_sheet import contact_sheet, display_maps
from render_jobs.exr import write_exr, write_image_exr
from render_jobs.results import ScreenMaps
from render_jobs.tonemap import to_uint8, tonemap
from shaderball.cli import Commands, human_bytes
from shaderball.progress import bar as progress_bar
from shaderball.signals import exit_stopped, stop_on_sigterm
from storage.errors import StoreError
from storage.image_files import check_picture_name, save_image
from storage.reader import Store
from storage.summary import list_shards, store_info, text_histogram
from storage.verify import verify as run_verify


def _open(url: str):
    return Store(url)


def _sample(store, index: int):
    try:
        return store.sample(index)
    except StoreError:
        raise
    except Exception as exc:  # noqa: BLE001 - corrupt bytes surface as decode errors
        raise click.ClickException(
            f"{store.url}: sample {index} is unreadable ({type(exc).__name__}: {exc})"
        ) from None


@click.group(cls=Commands, context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Inspect shaderball shard stores (local folders or s3:// URLs).

    \b
      shards info out/demo.zarr
      shards verify out/demo.zarr
      shards show out/demo.zarr --sample 0 -o sample.png
    """


@main.command("ls")
@click.argument("store")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
def ls_cmd(store, as_json):
    """List the shards of STORE: samples, bytes, and committed/pending/empty state.

    \b
    Example:
      shards ls out/dataset.zarr
    """
    rows = list_shards(_open(store))
    if as_json:
        click.echo(json.dumps(rows, indent=1))
        return
    table = [(r["shard"], r["samples"], human_bytes(r["bytes"]), r["state"]) for r in rows]
    click.echo(tabulate(table, ["shard", "samples", "bytes", "state"], colalign=("right",) * 3))


@main.command()
@click.argument("store")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of text.")
def info(store, as_json):
    """Schema, settings, counts per material kind, compression, sun and turbidity histograms.

    \b
    Example:
      shards info out/dataset.zarr
    """
    data = store_info(_open(store))
    if as_json:
        click.echo(json.dumps(data, indent=1))
        return
    lay, b = data["layout"], data["bytes"]
    ratio = f"{b['compression_ratio']:.2f}x" if b["compression_ratio"] else "n/a"
    lines = [
        f"store        {data['url']}",
        f"schema       v{data['schema_version']} (created {data['created']})",
        f"layout       {lay['num_materials']} materials x {lay['suns_per_material']} suns, "
        f"{lay['resolution']}px, {lay['shard_size']} samples/shard",
        f"shards       {data['shards']['committed']}/{data['shards']['total']} committed",
        f"samples      {data['samples']['committed']}/{data['samples']['total']} committed",
        "materials    "
        + (", ".join(f"{k} {v}" for k, v in data["materials_by_kind"].items()) or "none"),
        f"bytes        {human_bytes(b['stored'])} stored, {human_bytes(b['raw'])} raw ({ratio}), "
        f"{human_bytes(b['disk'])} on disk",
        "screen UV    " + _screen_uv_line(data["screen_uv"]),
        *_settings_lines(data["settings"]),
        "software     " + ", ".join(f"{k} {v}" for k, v in data["software"].items()),
        "sun elevation (degrees):",
        text_histogram(data["sun_elevation_deg"]),
        "turbidity:",
        text_histogram(data["turbidity"], fmt="{:>4.1f}-{:<4.1f}"),
    ]
    click.echo("\n".join(lines))


def _settings_lines(settings: dict) -> list[str]:
    """The dataset settings, one a line under ``settings`` (values as JSON)."""
    width = max(map(len, settings), default=0)
    return [
        f"{'settings' if i == 0 else '':<13}{k:<{width}}  {json.dumps(v)}"
        for i, (k, v) in enumerate(sorted(settings.items()))
    ] or ["settings     none"]


def _screen_uv_line(suv: dict | None) -> str:
    if suv is None:
        return "none (farm screen-uv STORE renders it: maps of new materials need it)"
    if "error" in suv:
        return f"UNUSABLE: {suv['error']}"
    s = suv["supersample"]
    return f"{s}x{s} sub-samples a pixel ({human_bytes(suv['bytes'])})"


@main.command()
@click.argument("store")
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
def verify(store, as_json):
    """Check checksums, commit records against data, NaN/Inf, value ranges and shapes.

    Exits 1 listing every bad shard and why; 0 when all committed shards are sound.

    \b
    Example:
      shards verify out/dataset.zarr
    """
    s = _open(store)
    bar = progress_bar(total=s.layout.num_shards, desc="verifying", unit="shard", disable=as_json)
    report = run_verify(s, progress=lambda _: bar.update(1))
    bar.close()
    if as_json:
        click.echo(
            json.dumps(
                {
                    "ok": report.ok,
                    "checked": report.checked,
                    "empty": report.empty,
                    "store_problems": report.store_problems,
                    "problems": {str(k): v for k, v in report.problems.items()},
                },
                indent=1,
            )
        )
    else:
        for p in report.store_problems:
            click.echo(f"store: {p}")
        for shard, reasons in sorted(report.problems.items()):
            for reason in reasons:
                click.echo(f"shard {shard}: {reason}")
        state = "OK" if report.ok else f"{len(report.problems)} bad shard(s)"
        click.echo(
            f"{state}: {report.checked} committed shard(s) checked, {report.empty} not written yet"
        )
    if not report.ok:
        sys.exit(1)


def _parse_range(text: str, total: int) -> range:
    try:
        if ":" in text:
            a, b = text.split(":", 1)
            r = range(int(a or 0), int(b) if b else total)
        else:
            r = range(int(text), int(text) + 1)
    except ValueError:
        raise click.BadParameter(
            f"{text!r} is not START:STOP or an index", param_hint="--samples"
        ) from None
    if r.start < 0 or r.stop > total or r.start >= r.stop:
        raise click.BadParameter(
            f"{text!r} is outside the store's 0:{total}", param_hint="--samples"
        )
    return r


@main.command()
@click.argument("store")
@click.option("--sample", "-s", "index", required=True, type=int, help="Sample index.")
@click.option("--out", "-o", required=True, type=click.Path(path_type=Path),
              help="the picture to write: .png, .jpg or .webp")  # fmt: skip
def show(store, index, out):
    """Write a labelled contact sheet of one sample: maps, mask, tonemapped render, light.

    \b
    Example:
      shards show out/dataset.zarr --sample 12 -o sample12.png
    """
    check_picture_name(out, "-o")
    s = _sample(_open(store), index)
    title = f"sample {s.index}  material {s.material_index} ({s.kind}: {s.source_id})"
    sheet = contact_sheet(ScreenMaps(**s.maps), [(s.render, s.sun.label())], title)
    save_image(sheet, out)
    click.echo(f"wrote {out}")


@main.command()
@click.argument("store")
@click.option("--out", "-o", "directory", required=True, type=click.Path(path_type=Path),
              help="the folder to write the files into (made if missing)")  # fmt: skip
@click.option("--samples", default="0:10", show_default=True, help="START:STOP or one index.")
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["png", "exr"]),
    default="png",
    show_default=True,
    help="png: tonemapped render + maps; exr: linear float.",
)
def export(store, directory, samples, fmt):
    """Export samples as image files (one render and one set of maps per sample).

    \b
    Examples:
      shards export out/dataset.zarr --samples 0:10 --format png -o exported/
      shards export s3://bucket/set.zarr --samples 5 --format exr -o one/
    """
    s = _open(store)
    wanted = _parse_range(samples, s.layout.num_samples)
    items = [_sample(s, i) for i in wanted]  # read (and fail) before writing anything
    directory.mkdir(parents=True, exist_ok=True)
    stop_on_sigterm()  # the temporary folder goes on SIGTERM as on Ctrl-C
    tmp = Path(tempfile.mkdtemp(prefix=".export.", dir=directory))
    try:
        for x in items:
            stem = f"sample_{x.index:06d}"
            if fmt == "exr":
                write_image_exr(tmp / f"{stem}_render.exr", x.render)
                write_exr(
                    tmp / f"{stem}_maps.exr",
                    {
                        f"{n}.{c}": a[i]
                        for n, a in x.maps.items()
                        for i, c in enumerate("RGB"[: a.shape[0]] if a.shape[0] > 1 else "Y")
                    },
                )
            else:
                Image.fromarray(to_uint8(tonemap(x.render))).save(tmp / f"{stem}_render.png")
                for name, img in display_maps(ScreenMaps(**x.maps)).items():
                    Image.fromarray(img).save(tmp / f"{stem}_{name}.png")
            (tmp / f"{stem}.json").write_text(
                json.dumps(
                    {
                        "sample": x.index,
                        "material": x.material_index,
                        "kind": x.kind,
                        "source_id": x.source_id,
                        "sun": x.sun.to_dict(),
                        "seed": x.seed,
                    }
                )
                + "\n"
            )
        for f in sorted(tmp.iterdir()):
            f.replace(directory / f.name)
    except KeyboardInterrupt:
        shutil.rmtree(tmp, ignore_errors=True)
        exit_stopped(f"the files already in {directory} are whole")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    click.echo(f"wrote {len(items)} sample(s) to {directory}")


if __name__ == "__main__":
    main()
