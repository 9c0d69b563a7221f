"""Benchmark results as files: each benchmark writes its tables to ``benchmarks/results/``
(one JSON file a table: title, the command that made it, the machine, the date, columns,
rows, notes), and ``python -m benchmarks.report`` renders every one of them into
``docs/benchmarks.md``. The figures in the docs are then always a benchmark's own output,
with the command and machine that gave them stated once per table.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import shlex
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

from storage.backend import write_atomic

#: where tables are written: ``benchmarks/results``, or ``$SHADERBALL_BENCH_RESULTS`` (the
#: tests point it at a temporary folder, so that they leave the repository's tables alone)
FOLDER = Path(
    os.environ.get("SHADERBALL_BENCH_RESULTS") or Path(__file__).resolve().parent / "results"
)


def cpu_name() -> str:
    """The CPU's model name and the cores this process may use."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {len(os.sched_getaffinity(0))} cores"


def command_line() -> str:
    """How this process was started, as ``python -m module args`` where it was so."""
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    argv = sys.argv[1:]
    head = ["python", "-m", spec.name] if spec is not None else ["python", *sys.argv[:1]]
    return shlex.join(head + argv)


@dataclass
class Table:
    """One table of results: ``rows`` of values in the order of ``columns``."""

    title: str
    columns: list[str]
    rows: list[list] = field(default_factory=list)
    command: str = field(default_factory=command_line)
    machine: str = field(default_factory=cpu_name)
    date: str = field(default_factory=lambda: datetime.date.today().isoformat())
    notes: list[str] = field(default_factory=list)

    def markdown(self) -> str:
        """The table as markdown: its title, the command, machine and date, the rows, notes."""
        lines = [
            f"### {self.title}",
            "",
            f"`{self.command}` on {self.machine}, {self.date}.",
            "",
            "| " + " | ".join(self.columns) + " |",
            "|" + "|".join("---" for _ in self.columns) + "|",
        ]
        lines += ["| " + " | ".join(_cell(v) for v in row) + " |" for row in self.rows]
        if self.notes:
            lines += [""] + [f"- {n}" for n in self.notes]
        return "\n".join(lines) + "\n"


def _cell(value) -> str:
    if value is None:
        return "—"
    if isinstance(value, int | float) and not isinstance(value, bool):
        return f"{value:,}"
    return str(value)


def save(name: str, table: Table, folder: Path = FOLDER) -> Path:
    """Write ``table`` to ``folder/NAME.json`` (atomically); returns the path."""
    path = Path(folder) / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    data = json.dumps(asdict(table), indent=1).encode()
    write_atomic(path, lambda f: f.write(data))
    return path


def load(path: Path) -> Table:
    return Table(**json.loads(Path(path).read_text()))
