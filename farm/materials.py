"""``farm materials``: the dry run of ``--materials``, with how every map of every file
material was read, and the error of every material that cannot be used. No Ray, no Blender:
the same loading code ``farm submit`` validates with (:func:`render_jobs.materials.sources.
read_material`), by the same pool of processes."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from farm.validate import InOrder
from render_jobs.errors import MaterialError
from render_jobs.materials.sources import read_material, specs_from_sources
from render_jobs.specs import MaterialSpec


@dataclass
class Entry:
    """One material of the dry run (``error`` set when it cannot be used)."""

    index: int
    kind: str
    source_id: str
    workflow: str = ""
    files: dict[str, str] = field(default_factory=dict)
    conversions: list[str] = field(default_factory=list)
    ignored: list[dict] = field(default_factory=list)  # {file, why}
    error: str | None = None


@dataclass
class DryRun:
    sources: list[str]
    entries: list[Entry]
    source_error: str | None = None  # a source string or folder that gives no materials

    @property
    def failed(self) -> int:
        return sum(e.error is not None for e in self.entries) + bool(self.source_error)

    def to_dict(self) -> dict:
        return {
            "sources": self.sources,
            "materials": [asdict(e) for e in self.entries],
            "usable": sum(e.error is None for e in self.entries),
            "failed": self.failed,
            "source_error": self.source_error,
        }


def dry_run(sources: list[str], seed: int = 0, progress=None) -> DryRun:
    """Every material of ``sources`` read and checked, by a pool of processes as ``farm
    submit`` validates (:class:`farm.validate.InOrder`); ``progress`` wraps the iteration."""
    try:
        specs = specs_from_sources(sources, seed)
    except MaterialError as exc:
        return DryRun(sources, [], str(exc))
    entries = InOrder(_entry, list(enumerate(specs)))
    return DryRun(sources, list(progress(entries) if progress else entries))


def _entry(item: tuple[int, MaterialSpec]) -> Entry:
    i, spec = item
    entry = Entry(i, spec.kind, spec.source_id)
    try:
        _, reading = read_material(spec)
    except MaterialError as exc:
        entry.error = str(exc)
    else:
        entry.workflow, entry.files = reading.workflow, dict(reading.files)
        entry.conversions = list(reading.conversions)
        entry.ignored = [{"file": f, "why": why} for f, why in reading.ignored]
    return entry


def format_dry_run(run: DryRun) -> str:
    """For people: file materials in full, generated ones one line per kind."""
    lines = []
    generated: dict[str, int] = {}
    for e in run.entries:
        if e.kind in ("uniform", "procedural") and e.error is None:
            generated[e.kind] = generated.get(e.kind, 0) + 1
            continue
        if e.error is not None:
            lines.append(f"FAILED  #{e.index} {e.source_id}: {e.error}")
            continue
        lines.append(f"ok      #{e.index} {e.source_id}  ({e.workflow})")
        lines += [f"          {name:<11} {file}" for name, file in e.files.items()]
        lines += [f"          converted   {c}" for c in e.conversions]
        lines += [f"          ignored     {i['file']}: {i['why']}" for i in e.ignored]
    for kind, n in generated.items():
        lines.append(f"ok      {n} {kind} material(s), generated from the seed")
    if run.source_error:
        lines.append(f"FAILED  {run.source_error}")
    usable = sum(e.error is None for e in run.entries)
    lines.append(f"{usable} usable, {run.failed} failed")
    return "\n".join(lines)
