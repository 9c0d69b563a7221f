"""The Cook-Torrance SVBRDF node graph, its screen-space AOVs, and texture swapping.

Material = Lambert (Diffuse BSDF, roughness 0) + GGX microfacet specular (Glossy BSDF, GGX,
no Fresnel term: the specular map is the reflectance), added. Four image textures on the UVs,
scaled by ``texture_tiling`` (twice as many repeats around as from pole to pole):

- diffuse (sRGB) → Diffuse colour; specular (sRGB) → Glossy colour;
- roughness (Non-Color) → Glossy roughness (Blender's r; alpha = r**2);
- normal (Non-Color, tangent space, OpenGL) → Normal Map node → both BSDFs' normals.

Each texture's value also goes to a shader AOV (``diffuse``, ``specular``, ``roughness``,
``normal``), plus ``mask`` = 1; Cycles writes AOVs at the camera ray's first hit, filtered like
the render, so they are the maps UV-mapped on the ball and rasterised, anti-aliased.

Texture swapping under persistent data (bpy 4.5): Cycles ignores pixel edits to an
existing image (``pixels.foreach_set`` + ``update``/``update_tag``/``pack``), and replacing
images by fresh ones is worse: a new image allocated where a removed one lived is served with
the removed one's pixels (specular rendered with last material's diffuse). So textures are
files: each material's maps are written as 8-bit PNGs under names never used before, and the
four image datablocks are pointed at them and reloaded; Cycles keys file textures by path.
8-bit is what the paper's maps are (PNG) and what the screen maps then show.
"""

from __future__ import annotations

import os
from pathlib import Path

from PIL import Image

from render_jobs.blender.bpy_guard import bpy
from render_jobs.materials.maps import MapBytes, MaterialMaps

AOVS = {
    "diffuse": "COLOR",
    "specular": "COLOR",
    "roughness": "VALUE",
    "normal": "COLOR",
    "mask": "VALUE",
}
#: the AOV of the UV map, present only while ``ShaderballRenderer.screen_uv`` renders
UV_AOV = "uv"
#: the AOVs of the geometry buffers (``render_jobs.screen_geometry``), world space, present
#: only while ``ShaderballRenderer.screen_uv`` renders
GEOMETRY_AOVS = {
    "geo_position": "COLOR",
    "geo_normal": "COLOR",
    "geo_tangent": "COLOR",
    "geo_bitangent": "COLOR",
    "geo_part": "VALUE",
}
_COLOUR_SPACE = {
    "diffuse": "sRGB",
    "specular": "sRGB",
    "roughness": "Non-Color",
    "normal": "Non-Color",
}


def register_aovs(view_layer) -> None:
    """Declare the screen-space AOV passes on ``view_layer``."""
    for name, kind in AOVS.items():
        aov = view_layer.aovs.add()
        aov.name = name
        aov.type = kind


def _aov(nodes, links, name: str, socket=None, value: float | None = None):
    node = nodes.new("ShaderNodeOutputAOV")
    node.aov_name = name
    if socket is not None:
        links.new(socket, node.inputs["Color" if AOVS[name] == "COLOR" else "Value"])
    if value is not None:
        node.inputs["Value"].default_value = value
    return node


class SvbrdfMaterial:
    """The ball's material: one node graph, textures swapped per material."""

    def __init__(self, texture_tiling: float):
        self.material = bpy.data.materials.new("svbrdf")
        self.material.use_nodes = True
        nt = self.material.node_tree
        nodes, links = nt.nodes, nt.links
        nodes.clear()
        self.uv = uv = nodes.new("ShaderNodeUVMap")
        uv.uv_map = "UVMap"
        mapping = nodes.new("ShaderNodeMapping")
        mapping.inputs["Scale"].default_value = (2 * texture_tiling, texture_tiling, 1.0)
        links.new(uv.outputs["UV"], mapping.inputs["Vector"])
        self.textures = {}
        for name in _COLOUR_SPACE:
            tex = nodes.new("ShaderNodeTexImage")
            tex.interpolation = "Linear"
            tex.extension = "REPEAT"
            links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
            self.textures[name] = tex
        diffuse = nodes.new("ShaderNodeBsdfDiffuse")
        diffuse.inputs["Roughness"].default_value = 0.0
        glossy = nodes.new("ShaderNodeBsdfGlossy")
        glossy.distribution = "GGX"
        normal_map = nodes.new("ShaderNodeNormalMap")
        normal_map.space = "TANGENT"
        normal_map.uv_map = "UVMap"
        add = nodes.new("ShaderNodeAddShader")
        out = nodes.new("ShaderNodeOutputMaterial")
        t = self.textures
        links.new(t["diffuse"].outputs["Color"], diffuse.inputs["Color"])
        links.new(t["specular"].outputs["Color"], glossy.inputs["Color"])
        links.new(t["roughness"].outputs["Color"], glossy.inputs["Roughness"])
        links.new(t["normal"].outputs["Color"], normal_map.inputs["Color"])
        links.new(normal_map.outputs["Normal"], diffuse.inputs["Normal"])
        links.new(normal_map.outputs["Normal"], glossy.inputs["Normal"])
        links.new(diffuse.outputs[0], add.inputs[0])
        links.new(glossy.outputs[0], add.inputs[1])
        links.new(add.outputs[0], out.inputs["Surface"])
        for name in _COLOUR_SPACE:
            _aov(nodes, links, name, socket=t[name].outputs["Color"])
        _aov(nodes, links, "mask", value=1.0)
        self._serial = 0
        self._files: list[Path] = []

    def add_uv_aov(self, view_layer):
        """Write the UV map (before the tiling) to an AOV named ``UV_AOV``; returns the
        view layer's AOV for :meth:`remove_uv_aov`."""
        aov = view_layer.aovs.add()
        aov.name, aov.type = UV_AOV, "COLOR"
        nt = self.material.node_tree
        self._uv_output = nt.nodes.new("ShaderNodeOutputAOV")
        self._uv_output.aov_name = UV_AOV
        nt.links.new(self.uv.outputs["UV"], self._uv_output.inputs["Color"])
        return aov

    def remove_uv_aov(self, view_layer, aov) -> None:
        self.material.node_tree.nodes.remove(self._uv_output)
        view_layer.aovs.remove(aov)

    def tangent_frame(self) -> dict:
        """Normal Map nodes (as the material's) fed a map of pure +x and of pure +y: their
        outputs are the directions that the map's x and y mean, by AOV name."""
        nodes = self.material.node_tree.nodes
        out = {}
        for name, colour in (
            ("geo_tangent", (1.0, 0.5, 0.5, 1.0)),
            ("geo_bitangent", (0.5, 1.0, 0.5, 1.0)),
        ):
            node = nodes.new("ShaderNodeNormalMap")
            node.space, node.uv_map = "TANGENT", "UVMap"
            node.inputs["Color"].default_value = colour
            out[name] = node
        return out

    def set_maps(self, maps: MaterialMaps | MapBytes, folder: Path) -> None:
        """Write ``maps`` as 8-bit PNGs under new names in ``folder`` and point the textures
        at them; the previous material's files are deleted (Cycles read them at its sync)."""
        if isinstance(maps, MaterialMaps):
            maps = MapBytes.of(maps)
        self._serial += 1
        stale, self._files = self._files, []
        for name, space in _COLOUR_SPACE.items():
            pixels = maps.arrays[name]
            path = folder / f"map-{os.getpid()}-{self._serial}-{name}.png"
            Image.fromarray(pixels[..., 0] if pixels.shape[2] == 1 else pixels).save(
                path, compress_level=1
            )
            self._files.append(path)
            tex = self.textures[name]
            if tex.image is None:
                tex.image = bpy.data.images.load(str(path))
            else:
                tex.image.filepath = str(path)
                tex.image.reload()
            tex.image.colorspace_settings.name = space
        for path in stale:
            path.unlink(missing_ok=True)


class GeometryAovs:
    """The geometry buffers' AOVs (:data:`GEOMETRY_AOVS`) on every material of the scene,
    for one render: position and shading normal (world space) and the object's pass index
    everywhere, the material's tangent frame on the ball. :meth:`remove` takes them away."""

    def __init__(self, view_layer, materials: list, ball: SvbrdfMaterial):
        self.view_layer = view_layer
        self.aovs = []
        for name, kind in GEOMETRY_AOVS.items():
            aov = view_layer.aovs.add()
            aov.name, aov.type = name, kind
            self.aovs.append(aov)
        self.added: list[tuple] = []  # (node tree, node)
        for mat in materials:
            nt = mat.node_tree
            geometry = nt.nodes.new("ShaderNodeNewGeometry")
            info = nt.nodes.new("ShaderNodeObjectInfo")
            sockets = {
                "geo_position": geometry.outputs["Position"],
                "geo_normal": geometry.outputs["Normal"],
                "geo_part": info.outputs["Object Index"],
            }
            frame = ball.tangent_frame() if mat == ball.material else {}
            sockets |= {k: node.outputs["Normal"] for k, node in frame.items()}
            made = [geometry, info, *frame.values()]
            for name, socket in sockets.items():
                out = nt.nodes.new("ShaderNodeOutputAOV")
                out.aov_name = name
                nt.links.new(
                    socket, out.inputs["Color" if GEOMETRY_AOVS[name] == "COLOR" else "Value"]
                )
                made.append(out)
            self.added += [(nt, node) for node in made]

    def remove(self) -> None:
        for nt, node in self.added:
            nt.nodes.remove(node)
        for aov in self.aovs:
            self.view_layer.aovs.remove(aov)


def neutral_material(name: str, grey: float, gloss: float = 0.0, roughness: float = 0.5):
    """A fixed grey diffuse (+ optional glossy) material for the pedestal and ground."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    diffuse = nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.inputs["Color"].default_value = (grey, grey, grey, 1.0)
    out = nodes.new("ShaderNodeOutputMaterial")
    if gloss > 0:
        glossy = nodes.new("ShaderNodeBsdfGlossy")
        glossy.inputs["Color"].default_value = (gloss, gloss, gloss, 1.0)
        glossy.inputs["Roughness"].default_value = roughness
        add = nodes.new("ShaderNodeAddShader")
        links.new(diffuse.outputs[0], add.inputs[0])
        links.new(glossy.outputs[0], add.inputs[1])
        links.new(add.outputs[0], out.inputs["Surface"])
    else:
        links.new(diffuse.outputs[0], out.inputs["Surface"])
    return mat
