"""The README's viewer picture: ``trainer viewer`` on a trained network, showing a held-out
material under one of its stored suns beside its Cycles render, screenshotted in headless
Chromium (the test command installs it).

The sample shown is not picked by eye: it is the procedural sample whose PSNR is the median
of the network's on the store's procedural samples (from ``trainer eval --per-sample`` scores,
as ``make quality`` keeps them), so the picture shows a typical held-out material, not the
best one. ``make quality`` runs this as its ``picture`` step; by hand:

    python -m benchmarks.viewer_picture --checkpoint out/quality/runs/unet \\
        --store out/quality/test.zarr --scores out/quality/scores/unet--test.csv \\
        -o docs/img/viewer.png

It prints the sample, its material and the PSNR the page shows, for the picture's caption.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

from benchmarks.quality_report import read_sample_table
from storage.reader import Store
from tests.servers import ServerProcess

VIEWPORT = {"width": 1400, "height": 1000}


@dataclass(frozen=True)
class Pick:
    """One test sample: its index, material, the material's sun, and the network's score."""

    sample: int
    material: int
    sun: int
    psnr: float


def median_sample(scores: dict, kinds: dict[int, str], suns: int, kind: str) -> Pick:
    """The sample of ``kind`` materials whose PSNR is the median of theirs (the lower of the
    middle two for an even count). ``scores``: per-sample lists ``sample``, ``material`` and
    ``psnr`` (``benchmarks.quality_report.per_sample``); ``kinds``: material → kind."""
    rows = [(p, s, m) for s, m, p in zip(scores["sample"], scores["material"], scores["psnr"],
                                         strict=True) if kinds.get(m) == kind]  # fmt: skip
    if not rows:
        raise ValueError(f"no {kind} material among the scored samples")
    psnr, sample, material = sorted(rows)[(len(rows) - 1) // 2]
    return Pick(int(sample), int(material), int(sample) - int(material) * suns, float(psnr))


def pick_sample(store_url: str, scores_csv: Path, kind: str = "procedural") -> Pick:
    """:func:`median_sample` of a store's samples as an eval CSV file scored them."""
    store = Store(store_url)
    kinds = {m: rec["kind"] for m, rec in store.materials().items()}
    return median_sample(read_sample_table(scores_csv), kinds, store.layout.suns_per_material,
                         kind)  # fmt: skip


def screenshot(checkpoint: Path, store_url: str, pick: Pick, out: Path) -> str:
    """Serve ``checkpoint`` with the store's materials, show the picked material under its
    stored sun beside Cycles, and save the page to ``out``; the page's PSNR line."""
    from playwright.sync_api import sync_playwright

    from tests.test_dashboard import chromium

    trainer = Path(sys.executable).parent / "trainer"
    cmd = [trainer, "viewer", "--checkpoint", checkpoint, "--store", store_url, "--device", "cpu"]
    with ServerProcess(cmd, "viewer", timeout=300) as server, sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium(), args=["--no-sandbox"])
        page = browser.new_page(viewport=VIEWPORT)
        page.goto(server.base + "/")
        page.click(f'.tile[data-id="s0:{pick.material}"]')
        page.click(f"#suns button >> nth={pick.sun}")
        page.wait_for_selector("#truth", state="visible", timeout=120_000)
        page.wait_for_function("document.getElementById('truth-psnr').textContent.includes('dB')")
        page.wait_for_timeout(1000)  # the thumbnails' lazy loads
        out.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(out), full_page=True)
        shown = page.locator("#truth-psnr").inner_text()
        browser.close()
    return shown


def make_picture(checkpoint: Path, store_url: str, scores_csv: Path, out: Path) -> dict:
    """Pick, screenshot, and what the caption needs (also kept as JSON beside ``out``)."""
    pick = pick_sample(store_url, scores_csv)
    shown = screenshot(checkpoint, store_url, pick, out)
    rec = Store(store_url).materials()[pick.material]
    found = re.search(r"(-?\d+(?:\.\d+)?) dB", shown)
    info = {**asdict(pick), "source": rec["source_id"], "kind": rec["kind"],
            "page_psnr": float(found.group(1)) if found else None, "page": shown.strip(),
            "picture": str(out)}  # fmt: skip
    out.with_suffix(".json").write_text(json.dumps(info, indent=1))
    return info


def describe(info: dict) -> str:
    return (f"{info['picture']}: material #{info['material']} ({info['source']}, "
            f"{info['kind']}) under its sun {info['sun'] + 1}: {info['psnr']:.2f} dB in eval, "
            f"the page: {info['page']}")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0].replace("\n", " "),
        epilog=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--checkpoint", type=Path, required=True, help="a run folder or checkpoint")
    ap.add_argument("--store", required=True, help="the held-out store the scores are of")
    ap.add_argument("--scores", type=Path, required=True,
                    help="the checkpoint's trainer eval --per-sample CSV on the store")  # fmt: skip
    ap.add_argument("-o", "--out", type=Path, default=Path("docs/img/viewer.png"))
    args = ap.parse_args()
    for path in (args.checkpoint, args.scores):
        if not path.exists():
            ap.error(f"{path}: no such file or folder")
    print(describe(make_picture(args.checkpoint, args.store, args.scores, args.out)))


if __name__ == "__main__":
    main()
