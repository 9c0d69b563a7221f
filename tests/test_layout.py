"""The code's layout, read from the source without importing it: no import cycles between the
project's modules; no import of a project module inside a function unless that module needs
an install extra (torch, Ray, Blender, the web server, ONNX) that the importing module does
not; training and rendering import each other's modules nowhere; the neutral ``shaderball``
package imports no other; and nothing reads outside the repository."""

from __future__ import annotations

import ast
import re
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("shaderball", "farm", "render_jobs", "storage", "trainer", "benchmarks")
#: the third-party packages that an install extra brings (pyproject.toml)
EXTRAS = {
    "torch": "train", "tensorboard": "train", "flip_evaluator": "train",
    "ray": "farm", "bpy": "render", "aiohttp": "dashboard", "jinja2": "dashboard",
    "prometheus_client": "dashboard", "onnx": "export", "onnxruntime": "export",
    "onnxscript": "export",
}  # fmt: skip


@cache
def modules() -> dict[str, Path]:
    out = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def resolve(name: str) -> str | None:
    """The project module ``name`` imports (a name inside a module resolves to the module)."""
    while name and name not in modules():
        name = name.rpartition(".")[0]
    return name or None


def imports(tree: ast.Module):
    """``(node, at_module_level, imported names)`` of every import in ``tree``."""
    top = set(tree.body)
    for node in tree.body:
        if isinstance(node, ast.If | ast.Try):
            top |= set(node.body)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield node, node in top, [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node, node in top, [f"{node.module}.{a.name}" for a in node.names]


@cache
def graph() -> tuple[dict[str, set[str]], dict[str, set[str]], list[tuple[str, int, str]]]:
    """Module-level project imports, module-level extras, and function-level project imports
    ``(module, line, imported module)``."""
    deps, extras, inner = {}, {}, []
    for name, path in modules().items():
        deps[name], extras[name] = set(), set()
        for node, top, names in imports(ast.parse(path.read_text())):
            for n in names:
                if top and n.split(".")[0] in EXTRAS:
                    extras[name].add(EXTRAS[n.split(".")[0]])
                target = resolve(n) if n.split(".")[0] in PACKAGES else None
                if target is None or target == name:
                    continue
                if top:
                    deps[name].add(target)
                else:
                    inner.append((name, node.lineno, target))
    return deps, extras, inner


@cache
def needs(name: str) -> frozenset[str]:
    """The extras importing ``name`` needs, through its module-level imports."""
    deps, extras, _ = graph()
    seen, todo, out = set(), [name], set()
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            out |= extras[m]
            todo += deps[m]
    return frozenset(out)


def cycles() -> list[list[str]]:
    deps = graph()[0]
    index, low, stack, on, found = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in deps[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while (w := stack.pop()) != v:
                on.discard(w)
                comp.append(w)
            on.discard(v)
            if comp:
                found.append(sorted([v, *comp]))

    for v in sorted(deps):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycles():
    assert cycles() == []


def test_imports_inside_functions_only_put_off_an_extra():
    late = [
        f"{m}:{line} imports {target}"
        for m, line, target in graph()[2]
        if not needs(target) - needs(m)
    ]
    assert late == []


def test_training_and_rendering_share_only_the_network():
    deps = graph()[0]
    for side, other in (("trainer.training", "trainer.rendering"),
                        ("trainer.rendering", "trainer.training")):  # fmt: skip
        crossing = [(m, sorted(d for d in deps[m] if d.startswith(other)))
                    for m in deps if m.startswith(side)]  # fmt: skip
        assert [c for c in crossing if c[1]] == []
    neutral = {d for m in deps if m.startswith("shaderball") for d in deps[m]}
    assert all(d.startswith("shaderball") for d in neutral), neutral
    production = [m for m in deps if not m.startswith("benchmarks")]
    assert [m for m in production if any(d.startswith("benchmarks") for d in deps[m])] == []


def test_nothing_reads_outside_the_repository():
    outside = re.compile(r"\.\./shared|parent\s*/\s*[\"']shared")
    hits = [
        str(p.relative_to(ROOT))
        for package in (*PACKAGES, "tests", "k8s", "docs")
        for p in (ROOT / package).rglob("*")
        if p.is_file() and p.suffix in (".py", ".md", ".yaml", ".sh") and p.name != "test_layout.py"
        and outside.search(p.read_text(errors="replace"))
    ]  # fmt: skip
    assert hits == []
