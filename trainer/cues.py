"""The names of the network's scene cues (``--inputs``) and their channels: plain data, free of
torch, for the training options; :mod:`trainer.scene` computes them."""

from __future__ import annotations

#: each cue and its channels, in the order they are concatenated
CUES = {
    "paint": 0,
    "geometry": 10,
    "light": 4,
    "normal": 3,
    "reflection": 3,
    "shadow": 1,
    "glossy": 3,
    "ambient": 3,
    "shade": 3,  # last: a residual network corrects the inputs' last three channels
}
#: the parts that carry the material's maps
MATERIAL_PARTS = ("ball", "ring", "core")
#: the cues that need the scene's geometry buffers
NEEDS_GEOMETRY = (
    "paint", "geometry", "normal", "reflection", "shadow", "glossy", "ambient", "shade",
)  # fmt: skip


def check_cues(cues: tuple[str, ...]) -> None:
    """Raise ``ValueError`` naming an unknown or repeated cue."""
    for i, c in enumerate(cues):
        if c not in CUES:
            raise ValueError(f"unknown input cue {c!r}: one of {', '.join(CUES)}")
        if c in cues[:i]:
            raise ValueError(f"input cue {c!r} is given twice")


def cue_channels(cues: tuple[str, ...]) -> int:
    return sum(CUES[c] for c in cues)


def ordered(cues) -> tuple[str, ...]:
    """``cues`` in :data:`CUES` order (the order their channels are concatenated)."""
    return tuple(c for c in CUES if c in set(cues))
