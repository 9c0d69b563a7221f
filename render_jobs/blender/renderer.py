"""The kept-loaded renderer: one Blender scene, material after material, sun after sun.

The scene (shaderball, camera, material graph, sky, lamp) is built once; per material only the
four textures change, per sun only sky and lamp, and ``use_persistent_data`` keeps Cycles'
BVH and kernels between renders. Cycles writes a multilayer EXR (Combined + AOVs) to a
scratch folder (the worker process puts it in ``/dev/shm``), read back with ``OpenEXR``.

Memory: images of a finished material are removed as the next one arrives, and orphan data
is purged every ``PURGE_EVERY`` materials; ``rss_bytes()`` lets the caller recycle the process
above a bound (Blender's memory grows over long runs of renders in one process).
"""

from __future__ import annotations

import contextlib
import os
import re
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import psutil

from render_jobs.blender import shaderball
from render_jobs.blender.bpy_guard import bpy
from render_jobs.blender.shading import (
    UV_AOV,
    GeometryAovs,
    SvbrdfMaterial,
    neutral_material,
    register_aovs,
)
from render_jobs.blender.sky import SkyAndSun
from render_jobs.errors import RenderError
from render_jobs.exr import read_layers
from render_jobs.geometry import MATERIAL_OBJECTS, geometry_hash
from render_jobs.geometry import shaderball as shaderball_meshes
from render_jobs.materials.maps import MapBytes, MaterialMaps
from render_jobs.results import MaterialRender, ScreenMaps, SunRender
from render_jobs.screen_geometry import PASS_INDEX, SCENE_MATERIALS, from_subsamples
from render_jobs.screen_uv import FILTER_WIDTH, PIXEL_FILTER, ScreenUV, filter_taps
from render_jobs.specs import RenderSettings, Sun

PURGE_EVERY = 16
_SAMPLE = re.compile(r"\| Sample (\d+)/(\d+)")


@contextlib.contextmanager
def _quiet_stdout():
    """Send Blender's C-level progress chatter on fd 1 to /dev/null for the duration."""
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


class _PathTracingClock:
    """Times Cycles' path tracing from its progress messages (first to last sample)."""

    def __init__(self) -> None:
        self.start: float | None = None
        self.end: float | None = None

    def reset(self) -> None:
        self.start = self.end = None

    def __call__(self, stats: str, *_args) -> None:
        m = _SAMPLE.search(stats)
        if m is None:
            return
        now = time.perf_counter()
        if self.start is None:
            self.start = now
        if m.group(1) == m.group(2):
            self.end = now

    @property
    def seconds(self) -> float:
        if self.start is None or self.end is None:
            return 0.0
        return self.end - self.start


def _configure_device(scene, settings: RenderSettings) -> None:
    if settings.device == "CPU":
        scene.cycles.device = "CPU"
        return
    prefs = bpy.context.preferences.addons["cycles"].preferences
    prefs.compute_device_type = settings.device
    prefs.get_devices()
    gpus = [d for d in prefs.devices if d.type == settings.device]
    if not gpus:
        raise RenderError(f"no {settings.device} device found for Cycles")
    for d in prefs.devices:
        d.use = d.type == settings.device
    scene.cycles.device = "GPU"


class ShaderballRenderer:
    """One loaded shaderball scene that renders :class:`MaterialMaps` under :class:`Sun`\\ s."""

    def __init__(self, settings: RenderSettings, scratch_dir: str | Path):
        self.settings = settings
        self.scratch = Path(scratch_dir)
        self.scratch.mkdir(parents=True, exist_ok=True)
        with _quiet_stdout():
            bpy.ops.wm.read_factory_settings(use_empty=True)
        scene = bpy.context.scene
        self.scene = scene
        self._configure(scene, settings)
        objects = shaderball.build_geometry(scene)
        camera = shaderball.build_camera(scene)
        self.material = SvbrdfMaterial(settings.texture_tiling)
        for name in MATERIAL_OBJECTS:
            objects[name].data.materials.append(self.material.material)
        floor, stand = SCENE_MATERIALS["floor"], SCENE_MATERIALS["stand"]
        self.neutral = [
            neutral_material(
                "pedestal", stand["diffuse"], gloss=stand["specular"], roughness=stand["roughness"]
            ),
            neutral_material("ground", floor["diffuse"]),
        ]
        objects["pedestal"].data.materials.append(self.neutral[0])
        objects["ground"].data.materials.append(self.neutral[1])
        for name, index in PASS_INDEX.items():  # the geometry buffers' parts
            objects[name].pass_index = index
        register_aovs(scene.view_layers[0])
        self.sky = SkyAndSun(scene)
        self.geometry_hash = shaderball.mesh_hash(objects, camera)
        self._clock = _PathTracingClock()
        bpy.app.handlers.render_stats.append(self._clock)
        self._materials_done = 0
        self._has_maps = False

    @staticmethod
    def _configure(scene, settings: RenderSettings) -> None:
        scene.render.engine = "CYCLES"
        _configure_device(scene, settings)
        cycles = scene.cycles
        cycles.samples = settings.samples
        cycles.use_adaptive_sampling = False
        cycles.use_denoising = settings.denoise
        cycles.use_preview_denoising = False
        if settings.denoise:  # OIDN on the final image, guided by albedo and normal
            cycles.denoiser = "OPENIMAGEDENOISE"
            cycles.denoising_input_passes = "RGB_ALBEDO_NORMAL"
            cycles.denoising_prefilter = "ACCURATE"
            scene.view_layers[0].cycles.use_denoising = True
        cycles.pixel_filter_type = PIXEL_FILTER  # the anti-aliasing render_jobs.screen_uv models
        cycles.filter_width = FILTER_WIDTH
        render = scene.render
        render.resolution_x = render.resolution_y = settings.resolution
        render.resolution_percentage = 100
        render.use_persistent_data = True
        render.film_transparent = False
        if settings.threads > 0:
            render.threads_mode = "FIXED"
            render.threads = settings.threads
        else:
            render.threads_mode = "AUTO"
        image = render.image_settings
        image.file_format = "OPEN_EXR_MULTILAYER"
        image.color_depth = "32"
        image.exr_codec = "NONE"
        scene.view_settings.view_transform = "Standard"

    def set_material(self, maps: MaterialMaps | MapBytes) -> float:
        """Swap in ``maps``; returns the seconds it took."""
        t0 = time.perf_counter()
        self.material.set_maps(maps, self.scratch)
        self._has_maps = True
        self._materials_done += 1
        if self._materials_done % PURGE_EVERY == 0:
            bpy.data.orphans_purge(do_local_ids=True, do_linked_ids=True, do_recursive=True)
        return time.perf_counter() - t0

    def render(self, sun: Sun, seed: int) -> tuple[SunRender, ScreenMaps]:
        """Render the current material under ``sun`` with Cycles seed ``seed``."""
        if not self._has_maps:
            raise RenderError("set_material() must come before render()")
        t0 = time.perf_counter()
        self.sky.set_sun(sun)
        self.scene.cycles.seed = seed
        path = self.scratch / f"render-{os.getpid()}.exr"
        self.scene.render.filepath = str(path)
        t1 = time.perf_counter()
        self._clock.reset()
        with _quiet_stdout():
            result = bpy.ops.render.render(write_still=True)
        t2 = time.perf_counter()
        if "FINISHED" not in result or not path.exists():
            raise RenderError(f"Cycles did not render (result {result})")
        layers = read_layers(path)
        path.unlink()
        t3 = time.perf_counter()
        combined = layers["Combined"][:3]
        maps = ScreenMaps(
            diffuse=layers["diffuse"][:3],
            specular=layers["specular"][:3],
            roughness=layers["roughness"][:1],
            normal=layers["normal"][:3],
            mask=layers["mask"][:1],
        )
        timings = {
            "scene": t1 - t0,
            "render": t2 - t1,
            "path_tracing": self._clock.seconds,
            "exr_read": t3 - t2,
            "total": t3 - t0,
        }
        return SunRender(sun=sun, seed=seed, radiance=combined, timings=timings), maps

    def render_material(
        self,
        maps: MaterialMaps | MapBytes,
        suns: list[Sun],
        seeds: list[int],
        progress: Callable[[int], None] | None = None,
    ) -> MaterialRender:
        """All suns of one material; the screen maps come from its first render.

        ``progress(k)`` is called after the k-th sun (k from 1).
        """
        if len(suns) != len(seeds) or not suns:
            raise ValueError("need one seed per sun, and at least one sun")
        upload = self.set_material(maps)
        renders, screen = [], None
        for sun, seed in zip(suns, seeds, strict=True):
            render, screen_maps = self.render(sun, seed)
            renders.append(render)
            screen = screen or screen_maps
            if progress is not None:
                progress(len(renders))
        assert screen is not None
        return MaterialRender(
            maps=screen,
            renders=renders,
            geometry_hash=self.geometry_hash,
            rss_bytes=rss_bytes(),
            material_seconds=upload,
        )

    def screen_uv(self, supersample: int) -> ScreenUV:
        """The ball's UV layout as the camera sees it (:class:`ScreenUV`), with the scene's
        geometry buffers (:mod:`render_jobs.screen_geometry`): the scene rendered once at
        ``supersample`` times the resolution, one sample per pixel at its centre (filter
        width 0.01), the UV map, a mask and the geometry written as AOVs; settings restored
        after."""
        if supersample < 1:
            raise ValueError(f"supersample must be >= 1, not {supersample}")
        scene, render, cycles = self.scene, self.scene.render, self.scene.cycles
        saved = {
            (render, "resolution_x"): render.resolution_x,
            (render, "resolution_y"): render.resolution_y,
            (cycles, "samples"): cycles.samples,
            (cycles, "filter_width"): cycles.filter_width,
            (cycles, "use_denoising"): cycles.use_denoising,
            (cycles, "max_bounces"): cycles.max_bounces,
        }
        path = self.scratch / f"screen-uv-{os.getpid()}.exr"
        uv_aov = self.material.add_uv_aov(scene.view_layers[0])
        materials = [self.material.material, *self.neutral]
        geometry = GeometryAovs(scene.view_layers[0], materials, self.material)
        try:
            render.resolution_x = render.resolution_y = self.settings.resolution * supersample
            cycles.samples, cycles.filter_width, cycles.max_bounces = 1, 0.01, 0
            cycles.use_denoising = False
            if not self._has_maps:  # any texture will do: only the UVs are read
                self.material.set_maps(_flat_maps(), self.scratch)
            render.filepath = str(path)
            with _quiet_stdout():
                result = bpy.ops.render.render(write_still=True)
            if "FINISHED" not in result or not path.exists():
                raise RenderError(f"Cycles did not render the UV layout (result {result})")
            layers = read_layers(path)
        finally:
            path.unlink(missing_ok=True)
            self.material.remove_uv_aov(scene.view_layers[0], uv_aov)
            geometry.remove()
            for (owner, name), value in saved.items():
                setattr(owner, name, value)
        hit = layers["mask"][0] > 0.5
        uv = np.where(hit[..., None], layers[UV_AOV][:2].transpose(1, 2, 0), 0.0)
        return ScreenUV(
            uv=np.ascontiguousarray(uv, dtype=np.float32),
            hit=hit,
            resolution=self.settings.resolution,
            supersample=supersample,
            texture_tiling=self.settings.texture_tiling,
            geometry_hash=geometry_hash(shaderball_meshes()),
            geometry=_geometry_buffers(layers, supersample),
        )


def _geometry_buffers(layers: dict, supersample: int):
    """The per-pixel geometry buffers from the supersampled render's AOVs."""
    world = {k: layers[k][:3].transpose(1, 2, 0) for k in ("geo_position", "geo_normal")}
    frame = {k: layers[k][:3].transpose(1, 2, 0) for k in ("geo_tangent", "geo_bitangent")}
    return from_subsamples(
        world["geo_position"],
        world["geo_normal"],
        frame["geo_tangent"],
        frame["geo_bitangent"],
        layers["geo_part"][0],
        supersample,
        filter_taps(supersample, FILTER_WIDTH),
    )


def _flat_maps() -> MaterialMaps:
    grey = np.full((4, 4, 1), 0.5, np.float32)
    flat = np.broadcast_to(np.array([0.5, 0.5, 1.0], np.float32), (4, 4, 3)).copy()
    return MaterialMaps(np.repeat(grey, 3, 2), np.repeat(grey, 3, 2), grey, flat, "flat")


def rss_bytes() -> int:
    """Resident memory of this process, bytes."""
    return psutil.Process().memory_info().rss
