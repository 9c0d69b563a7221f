"""Which file of a material folder is which map, and which workflow the folder is in.

Folders come as material libraries and tools name them: ambientCG (``*_Color``,
``*_Roughness``, ``*_Metalness``, ``*_NormalGL`` / ``*_NormalDX``), Poly Haven (``*_diff_*``,
``*_rough_*``, ``*_metal_*``, ``*_nor_gl_*`` / ``*_nor_dx_*``, packed ``*_arm_*``), Substance
exports (``*_BaseColor``, ``*_Metallic``, ``*_Roughness``, ``*_Normal``), spec-gloss sets
(``diffuse``, ``specular``, ``glossiness``) and glTF's packed ``orm``. A file's name is split
into lower-case words at ``_``, ``-``, ``.`` and spaces; the role word that comes *last* names
its map (``metal_plate_diff_2k`` is a diffuse map). Maps this renderer does not use (AO,
height, displacement, opacity, emission, ...) and names that say nothing are listed as ignored,
never errors.

The rules (:func:`plan_folder`), in order:

1. **Workflow.** A specular map makes the folder spec-gloss: the explicit diffuse map is the
   diffuse (a base colour stands in when there is none); metallic and packed maps are ignored
   but for the roughness a packed map may give. Otherwise it is metal-rough: the base colour
   (or a diffuse map when there is none, as Poly Haven names it) with a metallic map, the blue
   channel of a packed ARM/ORM map, or none (metallic 0, a dielectric).
2. **Roughness**: a roughness map, else a glossiness map (inverted), else the green channel of
   a packed map; none is an error.
3. **Normal**: OpenGL-marked first, then an unmarked one (taken as OpenGL, as glTF and most
   exporters write them), then a DirectX-marked one (green flipped); none: flat.
4. Two files for one map that the chosen rules use (two base colours, two roughness maps) is
   ambiguous: a one-line error naming both.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from render_jobs.errors import MaterialError
from render_jobs.materials.images import SUFFIXES

#: role -> name patterns (consecutive words); the order breaks ties at one position
ROLES: dict[str, tuple[tuple[str, ...], ...]] = {
    "normal_dx": (("normaldx",), ("normaldirectx",), ("nor", "dx"), ("nrm", "dx"),
                  ("normal", "dx"), ("normal", "directx")),
    "normal_gl": (("normalgl",), ("normalopengl",), ("nor", "gl"), ("nrm", "gl"),
                  ("normal", "gl"), ("normal", "opengl")),
    "normal": (("normal",), ("normals",), ("nor",), ("nrm",), ("norm",)),
    "packed": (("arm",), ("orm",)),
    "basecolor": (("basecolor",), ("basecolour",), ("base", "color"), ("base", "colour"),
                  ("color",), ("colour",), ("col",), ("albedo",)),
    "diffuse": (("diffuse",), ("diff",)),
    "specular": (("specular",), ("spec",)),
    "roughness": (("roughness",), ("rough",)),
    "glossiness": (("glossiness",), ("gloss",)),
    "metallic": (("metallic",), ("metalness",), ("metal",)),
}  # fmt: skip
#: words of maps this renderer does not use
UNUSED = {
    "ao", "ambientocclusion", "occlusion", "height", "displacement", "disp", "bump", "opacity",
    "alpha", "transparency", "emission", "emissive", "emit", "cavity", "curvature",
    "translucency", "sss", "subsurface", "idmap", "mask", "preview", "thumbnail", "thumb",
}  # fmt: skip
LABELS = {
    "diffuse": "diffuse", "basecolor": "base colour", "specular": "specular",
    "roughness": "roughness", "glossiness": "glossiness", "metallic": "metallic",
    "packed": "packed ARM/ORM", "normal": "normal", "normal_gl": "OpenGL normal",
    "normal_dx": "DirectX normal",
}  # fmt: skip


def words(name: str) -> list[str]:
    return [w for w in re.split(r"[\W_]+", Path(name).stem.lower()) if w]


def role_of(name: str) -> str | None:
    """The map a file name names (``None``: nothing this renderer uses, or nothing known)."""
    ws = words(name)
    best: tuple[int, int, str] | None = None  # (position, -priority, role)
    for priority, (role, patterns) in enumerate(ROLES.items()):
        for pat in patterns:
            for i in range(len(ws) - len(pat) + 1):
                if tuple(ws[i : i + len(pat)]) == pat:
                    key = (i + len(pat) - 1, -priority, role)
                    best = key if best is None or key > best else best
    unused = [i for i, w in enumerate(ws) if w in UNUSED]
    if unused and (best is None or unused[-1] > best[0]):
        return None
    return best[2] if best else None


def image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SUFFIXES)


@dataclass
class FolderPlan:
    """How a per-map folder is read: its workflow, the file of each map it uses, how each
    becomes this renderer's map, and every other file with why it is not used."""

    folder: Path
    workflow: str  # "spec-gloss" | "metal-rough"
    files: dict[str, Path]  # diffuse | basecolor, specular | metallic | packed, roughness ...
    roughness_from: str  # "roughness" | "glossiness" | "packed"
    metallic_from: str | None  # "metallic" | "packed" | None (metal-rough only)
    normal_from: str | None  # "normal_gl" | "normal" | "normal_dx" | None (flat)
    ignored: list[tuple[str, str]] = field(default_factory=list)  # (file name, why)
    notes: list[str] = field(default_factory=list)


def classify(folder: Path) -> tuple[dict[str, list[Path]], list[tuple[str, str]]]:
    """Files by map, and the files no map uses with why."""
    by_role: dict[str, list[Path]] = {}
    ignored = []
    for p in image_files(folder):
        role = role_of(p.name)
        if role is None:
            known = any(w in UNUSED for w in words(p.name))
            ignored.append((p.name, "a map this renderer does not use" if known else
                            "the name names no map"))  # fmt: skip
        else:
            by_role.setdefault(role, []).append(p)
    return by_role, ignored


def looks_like_material(folder: Path) -> bool:
    """True when the file names in ``folder`` name at least two different maps."""
    return len(classify(folder)[0]) >= 2


def _one(folder: Path, by_role: dict[str, list[Path]], role: str) -> Path:
    paths = by_role[role]
    if len(paths) > 1:
        names = ", ".join(p.name for p in paths)
        raise MaterialError(f"{folder}: ambiguous {LABELS[role]} map: {names}")
    return paths[0]


def plan_folder(folder: Path) -> FolderPlan:
    """Apply the module's rules to ``folder``; raises :class:`MaterialError` in one line."""
    by_role, ignored = classify(folder)
    used: dict[str, Path] = {}
    notes: list[str] = []

    def take(role: str, as_: str | None = None) -> None:
        used[as_ or role] = _one(folder, by_role, role)

    if "specular" in by_role:
        workflow = "spec-gloss"
        colour = "diffuse" if "diffuse" in by_role else "basecolor"
        if colour not in by_role:
            raise MaterialError(f"{folder}: no diffuse map (a specular map makes it spec-gloss)")
        take(colour, "diffuse")
        if colour == "basecolor":
            notes.append(f"base colour {used['diffuse'].name} used as the diffuse map")
        take("specular")
        metallic_from = None
    else:
        workflow = "metal-rough"
        colour = "basecolor" if "basecolor" in by_role else "diffuse"
        if colour not in by_role:
            raise MaterialError(
                f"{folder}: no base colour or diffuse map (expected a name with color, "
                "basecolor, albedo, diffuse or diff)"
            )
        take(colour, "basecolor")
        metallic_from = "metallic" if "metallic" in by_role else None
        metallic_from = metallic_from or ("packed" if "packed" in by_role else None)
        if metallic_from:
            take(metallic_from)
        else:
            notes.append("no metallic map: metallic 0 (a dielectric)")
    for role in ("roughness", "glossiness", "packed"):
        if role in by_role:
            roughness_from = role
            break
    else:
        raise MaterialError(
            f"{folder}: no roughness map (expected a name with roughness, rough, glossiness, "
            "gloss, or a packed arm/orm map)"
        )
    take(roughness_from)
    normal_from = next((r for r in ("normal_gl", "normal", "normal_dx") if r in by_role), None)
    if normal_from:
        take(normal_from, "normal")
    else:
        notes.append("no normal map: flat")
    chosen = set(used.values())
    for role, paths in by_role.items():
        for p in paths:
            if p not in chosen:
                ignored.append((p.name, f"{LABELS[role]} map, not used by the {workflow} rules"))
    ignored.sort()
    return FolderPlan(
        folder, workflow, used, roughness_from, metallic_from, normal_from, ignored, notes
    )
