"""The viewer's page: one Jinja2 template (``templates/viewer.html``, autoescaped), its CSS
and its JavaScript (``static/``), files of the package inlined into the page; nothing is
loaded from elsewhere.

The script keeps the page's state (material id, edits, light), asks ``/api/frame`` for a new
image whenever any of it changes, with at most one request in flight and the latest state
sent next (so dragging the sun never queues stale frames), and shows the ``Server-Timing``
parts. The sun is dragged on an SVG hemisphere seen from above: the centre is the zenith,
the rim the horizon, the camera at the bottom (it looks along +Y); distance from the centre
is 90° minus the elevation. "Turn the sun" moves it round the sky at its elevation until
stopped (or dragged), as fast as frames come, and shows the frames a second.
"""

from __future__ import annotations

from importlib import resources

from jinja2 import Environment, PackageLoader, select_autoescape
from markupsafe import Markup

from shaderball.web import ICON_LINK

#: the page's template (``templates/viewer.html``), and its CSS and JavaScript (``static/``),
#: which the page inlines: package data, read once
_ENV = Environment(
    loader=PackageLoader("trainer.rendering.viewer", "templates"),
    autoescape=select_autoescape(default=True, default_for_string=True),
)
_PAGE = _ENV.get_template("viewer.html")
STATIC = resources.files("trainer.rendering.viewer") / "static"
CSS = (STATIC / "viewer.css").read_text()
SCRIPT = (STATIC / "viewer.js").read_text()


def render(secret: str, info: dict, materials: list[dict]) -> str:
    return _PAGE.render(
        secret=secret,
        info=info,
        materials=materials,
        state={"materials": materials, "info": info},
        css=Markup(CSS),
        script=Markup(SCRIPT),
        icon=Markup(ICON_LINK),
    )
