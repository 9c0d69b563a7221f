"""``trainer viewer``: any material on the shaderball through a trained network, in a web page
where the material is picked, uploaded, built or edited and the sun is dragged.

- ``materials``: the gallery, uploads, the uniform builder and the edits (no web);
- ``engine``: frames (mapping, network, encoding, each timed) and the ground-truth view;
- ``app``: the aiohttp server on :mod:`shaderball.web` (loopback by default, token otherwise);
- ``page``: the page's HTML, CSS and JavaScript, all written here.
"""

#: the largest upload, all files together, by default (an 8K PNG set): here, apart from
#: :mod:`trainer.rendering.viewer.materials`, so that ``trainer viewer --help`` imports no torch
MAX_UPLOAD_MB = 1024
