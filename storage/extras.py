"""Which install extra each part needs, and one line saying so when it is missing.

``pip install shaderball`` is the store and the material readers; the roles add extras:
``[render]`` (bpy: the render workers, ``farm preview``), ``[farm]`` (Ray: ``farm submit``),
``[train]`` (torch: ``trainer``), ``[dashboard]`` (``farm dashboard``), ``[export]`` (ONNX:
``trainer export``), ``[all]``. This module lives in ``storage`` because every role installs
it.
"""

from __future__ import annotations

import importlib.util

from shaderball.errors import UserError

#: module -> the extra that installs it
EXTRA_OF = {
    "bpy": "render",
    "ray": "farm",
    "torch": "train",
    "aiohttp": "dashboard",
    "jinja2": "dashboard",
    "prometheus_client": "dashboard",
    "onnx": "export",
    "onnxscript": "export",
    "onnxruntime": "export",
}


class MissingExtra(UserError, RuntimeError):
    """A part was used without the extra that installs what it needs."""


def require(what: str, *modules: str) -> None:
    """Raise :class:`MissingExtra` naming the extra to install when a module is missing."""
    for name in modules:
        if importlib.util.find_spec(name) is None:
            extra = EXTRA_OF[name]
            raise MissingExtra(
                f"{what} needs {name}, which this install lacks: pip install 'shaderball[{extra}]'"
            )
