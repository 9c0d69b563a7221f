"""Put what a ``bash benchmarks/gpu.sh learn`` device call brought back in place, and score its
networks here.

    python -m benchmarks.gpu_learn_back FOLDER        # or: make gpu-learn-back FROM=FOLDER

FOLDER holds the call's files: the table ``learning-gpu.json`` and its grid
``learning-gpu.png``, the log ``gpu-bench.txt``, ``learning-rows.tgz`` (each row's grid and
training log) and each row's network slimmed (``trainer slim``) in parts,
``learning-ROW.pt.0``, ``.1``, ... The table goes to ``benchmarks/results`` (``make
bench-report`` shows it in docs/benchmarks.md) with its grid in ``docs/img``; each row's parts
are joined into ``INTO/ROW.pt`` and the archive is unpacked into ``INTO/rows``. Then ``trainer
eval`` scores the networks (and any ``--also``, such as a CPU run on the same store) on the
same samples, paired: on the run's held-out materials, its store at its address here
(``--store``), and on materials no store holds (``--on``: ``make learn-test-store``), each
table saved in ``INTO/eval-*.txt`` beside its grid. A row whose network stayed behind (the log
says why) is scored from the table alone; a missing table, or a network missing a part, is
one line before anything is copied, and so is an archive that does not unpack.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

from benchmarks import results
from benchmarks.learning import DOC_IMG, grid_note
from storage.backend import write_atomic

NAME = "learning-gpu"
PART = re.compile(r"^learning-(?P<row>.+)\.pt\.(?P<index>\d+)$")


class Incomplete(ValueError):
    """The device call's files are not all there."""


def networks(folder: Path) -> dict[str, list[Path]]:
    """Each row's parts in order; :class:`Incomplete` where one is missing."""
    found: dict[str, dict[int, Path]] = {}
    for path in folder.iterdir():
        if m := PART.match(path.name):
            found.setdefault(m["row"], {})[int(m["index"])] = path
    for row, parts in found.items():
        if sorted(parts) != list(range(len(parts))):
            missing = min(set(range(max(parts) + 1)) - set(parts))
            raise Incomplete(f"{folder}: learning-{row}.pt.{missing} is missing")
    return {row: [parts[i] for i in sorted(parts)] for row, parts in sorted(found.items())}


def join(parts: list[Path], into: Path) -> Path:
    """The parts, one after the other, in ``into`` (written atomically; one part: a copy)."""

    def write(f) -> None:
        for part in parts:
            with open(part, "rb") as src:
                shutil.copyfileobj(src, f)

    write_atomic(into, write)
    return into


def unpack(archive: Path, into: Path) -> None:
    """The archive's files in the folder ``into``, unpacked beside it first: a bad archive or
    a kill leaves the folder as it was, never a part of either."""
    into.parent.mkdir(parents=True, exist_ok=True)
    fresh = Path(tempfile.mkdtemp(prefix=f".{into.name}.new.", dir=into.parent))
    old = fresh.with_name(fresh.name.replace(".new.", ".old."))
    try:
        with tarfile.open(archive) as tar:
            tar.extractall(fresh, filter="data")
        if into.exists():
            into.rename(old)
        fresh.rename(into)
    except BaseException:
        shutil.rmtree(fresh, ignore_errors=True)
        if old.exists() and not into.exists():
            old.rename(into)  # the new files did not go in: the earlier ones go back
        raise
    shutil.rmtree(old, ignore_errors=True)


def evaluate(checkpoints: list[Path | str], extra: list[str], grid: Path) -> str:
    """``trainer eval`` of ``checkpoints`` on the same samples; its printed tables."""
    argv = [sys.executable, "-m", "trainer.cli", "eval", "--device", "cpu", "--grid", str(grid)]
    for c in checkpoints:
        argv += ["--checkpoint", str(c)]
    r = subprocess.run(argv + extra, capture_output=True, text=True)
    if r.returncode:
        return f"trainer eval failed: {(r.stderr.strip().splitlines() or ['?'])[-1]}\n"
    return r.stdout


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("folder", type=Path, help="the device call's files")
    p.add_argument("--into", type=Path, default=Path("out/gpu-learn"),
                   help="where the networks, the rows' files and the scores go")  # fmt: skip
    p.add_argument("--store", default="out/gpu-learn-64-1100.zarr",
                   help="the store the call trained on, as it is here")  # fmt: skip
    p.add_argument("--on", default="out/learn-test-64.zarr",
                   help="a store of materials no store holds ('' to skip)")  # fmt: skip
    p.add_argument("--also", action="append", default=[], metavar="CHECKPOINT",
                   help="score this network beside them (repeatable): one trained on the "
                   "same store, as trainer eval refuses one that trained on the call's held-out "
                   "materials")  # fmt: skip
    p.add_argument("--results", type=Path, default=results.FOLDER)
    p.add_argument("--pictures", type=Path, default=DOC_IMG)
    return p


def main(argv: list[str] | None = None) -> None:
    p = parser()
    args = p.parse_args(argv)
    table_file = args.folder / f"{NAME}.json"
    if not table_file.is_file():
        p.error(f"{table_file} is missing: the call wrote no table (see its gpu-bench.txt)")
    try:
        parts = networks(args.folder)
    except Incomplete as exc:
        p.error(str(exc))
    table = results.load(table_file)
    rows_archive = args.folder / "learning-rows.tgz"
    if rows_archive.is_file():
        try:
            unpack(rows_archive, args.into / "rows")
        except tarfile.TarError as exc:
            p.error(f"{rows_archive}: not an archive that unpacks ({exc})")
    grid = args.folder / f"{NAME}.png"
    if grid.is_file():
        join([grid], args.pictures / f"{NAME}.png")
        note = grid_note(NAME, [str(row[0]) for row in table.rows])
        if note not in table.notes:
            table.notes.append(note)
    print(f"table: {results.save(NAME, table, args.results)}")
    joined = [join(pieces, args.into / f"{row}.pt") for row, pieces in parts.items()]
    for path in joined:
        print(f"network: {path}")
    scored = [*joined, *args.also]
    if not scored:
        print("no networks came back: the rows' figures are in the table alone")
        return
    score(scored, args)


def score(scored: list[Path | str], args: argparse.Namespace) -> None:
    """``trainer eval`` of the networks on the run's held-out materials and, with ``--on``,
    on unseen ones: each table printed and kept in ``INTO/eval-NAME.txt``."""
    args.into.mkdir(parents=True, exist_ok=True)
    runs = [("heldout", ["--store", args.store])]
    if args.on:
        runs.append(("unseen", ["--on", args.on]))
    for name, extra in runs:
        said = evaluate(scored, extra, args.into / f"eval-{name}.png")
        (args.into / f"eval-{name}.txt").write_text(said)
        print(f"\n== {name} ({' '.join(extra)})\n{said}", end="")


if __name__ == "__main__":
    main()
