"""The network's scene inputs: what the fixed camera sees of the scene, and cheap shading of it.

The paper's network sees only the material maps (zeros off the ball) and a light vector
at its bottleneck. Every render shares the camera, the ball, the stand and the floor, so the
per-pixel geometry (``render_jobs.screen_geometry``, rendered once by Blender and kept with
each store and checkpoint) can be given too, and from it and the sun a cheap analytic
shading. :class:`SceneInputs` computes the chosen cues (:data:`CUES`) from a batch's maps and
light and concatenates them after the maps:

- ``paint``: the maps outside the material painted with the floor's and the stand's own
  (constant) materials, and white where the camera sees sky, so every pixel says what it is
  (the authors' released inputs paint the parts of their scene alike);
- ``geometry`` (10): camera-space surface normal (3), inverse depth (1, ``3 / depth``), and
  the pixel's coverage of each part of the scene (6: sky, floor, stand, ball, ring, core);
- ``light`` (4): the sun direction in camera space and turbidity / 10, as constant planes at
  full resolution (the paper's light encoder reaches only the bottleneck);
- ``normal`` (3): the shading normal in camera space, the normal map turned by the
  material's tangent frame;
- ``reflection`` (3): the view direction mirrored about the shading normal, in world space
  (z up): where a glossy surface reflects the sky and where the floor;
- ``shadow`` (1): the sun's visibility, a ray from each pixel's surface towards the sun
  tested against the scene's analytic shadow casters (``render_jobs.geometry.occluders``);
- ``glossy`` (3): the sky and the floor seen in the specular lobe: the specular reflectance
  times GGX's directional albedo (Karis 2014's analytic fit) times the light that arrives
  along the reflected view direction (the sky's or the sun-lit floor's, blended across the
  horizon over a width that grows with roughness), tonemapped; 0 where the camera sees sky.
  The ``shade`` cue's sky term is diffuse only, so without this cue a glossy material's
  colour under the sky is left to the network (it learnt less per image pass with the cue
  than without: docs/training.md; the default recipe leaves it out);
- ``ambient`` (3): every surface lit by the sky above and the sun-lit floor below (Lambert,
  each in its share of the surface's hemisphere), plus the ``glossy`` term, tonemapped; 0
  where the camera sees sky. Where the sun does not reach the ball, the ``shade`` cue's sky
  term is a few times darker than the renders, this one close to them (the floor's light
  is most of it); in the default recipe (at 16k image passes it made no difference, at 64k
  it learnt more per pass: docs/training.md);
- ``shade`` (3): Cook-Torrance under the sun lamp (Lambert + GGX as the renderer's
  material, the lamp's strength and colour from ``render_jobs.sun``), times the sun's
  visibility, plus a hemispherical sky term, tonemapped as the targets are; mid-grey
  where the camera sees sky.

Shapes: maps ``(N, 9 + r, H, W)`` in [0, 1] (``trainer.targets.model_inputs``), light
``(N, 4)``; out ``(N, 9 + r + channels(cues), H, W)``. Everything is a differentiable torch
expression of the inputs and constant buffers, so ONNX export and every inference path run it.

The cues run every training step on the GPU, so they make no tensor from host data (a
Python list as an index, ``torch.tensor(values, device=...)``): copying one to the device
waits until the device has run every step queued before, and the host then queues the rest
of the step while the device idles. Constants are Python numbers, buffers or slices.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from render_jobs import sun as sunlib
from render_jobs.screen_geometry import PARTS, ScreenGeometry, camera_rays, half_width
from trainer.cues import MATERIAL_PARTS, check_cues, cue_channels, ordered
from trainer.targets import TURBIDITY_SCALE, Tonemap, srgb_decode, srgb_encode

#: horizontal irradiance of the sky alone, W/m² (Blender's Hosek-Wilkie at strength 1, as
#: ``render_jobs.sun.SUN_ZENITH_IRRADIANCE``'s comment gives it)
SKY_IRRADIANCE = 0.25
#: what the shade cue holds where the camera sees sky (mid-grey: a residual network's
#: neutral start there)
SKY_SHADE = 0.5
#: the least GGX alpha shaded (a mirror's sun highlight would be a single huge pixel)
MIN_ALPHA = 0.02
#: GGX's directional albedo with no Fresnel term, ``1 - GLOSSY_LOSS * r`` at Blender roughness
#: ``r`` (Karis 2014, "Physically Based Shading on Mobile": the analytic environment BRDF at
#: F0 = 1, where its view-angle terms cancel)
GLOSSY_LOSS = 0.55
#: the narrowest blend of sky and floor across the horizon, in the reflected ray's z
HORIZON_BLEND = 0.05
#: how far a shadow ray starts off its surface, metres
RAY_OFFSET = 2e-3


def _rows(parts: tuple[str, ...]) -> slice:
    """The rows of ``parts`` in the ``parts`` buffer, a slice (see the module docstring)."""
    idx = [PARTS.index(p) for p in parts]
    if idx != list(range(idx[0], idx[-1] + 1)):
        raise ValueError(f"the parts {parts} are not next to each other in {PARTS}")
    return slice(idx[0], idx[-1] + 1)


#: the material's parts' rows in the ``parts`` buffer, and every other part's
MATERIAL_ROWS = _rows(MATERIAL_PARTS)
OTHER_ROWS = _rows(tuple(p for p in PARTS if p not in MATERIAL_PARTS))


class SceneInputs(nn.Module):
    """The maps with the cues ``cues`` concatenated (see the module docstring).

    ``geometry`` fills the constant buffers; without it they are zeros of the right shapes,
    for a checkpoint's ``load_state_dict`` to fill. ``exposure`` is the targets' tonemap's."""

    def __init__(
        self,
        cues: tuple[str, ...],
        resolution: int,
        roughness_channels: int,
        exposure: float,
        geometry: ScreenGeometry | None = None,
    ):
        super().__init__()
        check_cues(cues)
        self.cues = ordered(cues)
        self.r = roughness_channels
        self.tonemap = Tonemap(exposure=exposure)
        n = resolution
        self.register_buffer("position", torch.zeros(3, n, n))
        self.register_buffer("normal", torch.zeros(3, n, n))
        self.register_buffer("tangent", torch.zeros(3, n, n))
        self.register_buffer("bitangent", torch.zeros(3, n, n))
        self.register_buffer("parts", torch.zeros(len(PARTS), n, n))
        self.register_buffer("camera_to_world", torch.eye(3))
        self.register_buffer("camera_location", torch.zeros(3))
        self.register_buffer("part_materials", torch.zeros(len(PARTS), 3))  # diffuse, spec, r
        self.register_buffer("spheres", torch.zeros(0, 9))  # centre, radius, axis, lo, hi
        self.register_buffer("frustums", torch.zeros(0, 4))  # z0, z1, r0, r1
        self.register_buffer("rays", _rays(n, half_width()), persistent=False)
        if geometry is not None:
            self.set_geometry(geometry)

    @torch.no_grad()
    def set_geometry(self, g: ScreenGeometry) -> None:
        """Fill the buffers from ``g``."""
        for name in ("position", "normal", "tangent", "bitangent", "parts"):
            getattr(self, name).copy_(torch.from_numpy(getattr(g, name)))
        self.camera_to_world.copy_(torch.tensor(g.camera_to_world))
        self.camera_location.copy_(torch.tensor(g.camera_location))
        self.rays.copy_(_rays(self.rays.shape[-1], g.half_width))
        mats = torch.zeros(len(PARTS), 3)
        mats[PARTS.index("sky")] = torch.tensor([1.0, 1.0, 1.0])
        for part, m in g.materials.items():
            mats[PARTS.index(part)] = torch.tensor([m["diffuse"], m["specular"], m["roughness"]])
        self.part_materials.copy_(mats)
        spheres = [
            [*s["centre"], s["radius"], *s["axis"], s["lo"], s["hi"]]
            for s in g.occluders["spheres"]
        ]
        frustums = [[f["z0"], f["z1"], f["r0"], f["r1"]] for f in g.occluders["frustums"]]
        device = self.position.device
        self.spheres = torch.tensor(spheres, dtype=torch.float32, device=device).view(-1, 9)
        self.frustums = torch.tensor(frustums, dtype=torch.float32, device=device).view(-1, 4)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        for name in ("spheres", "frustums"):  # their count is the checkpoint's
            key = prefix + name
            if key in state_dict:
                here = getattr(self, name).device
                setattr(self, name, torch.empty(state_dict[key].shape, device=here))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @property
    def out_channels(self) -> int:
        return 9 + self.r + cue_channels(self.cues)

    def _apply(self, fn, recurse=True):
        """Moves keep the buffers in float32 (a network cast to bf16 would otherwise round
        the positions by centimetres and the shadows with them); only the device follows."""
        device = fn(torch.zeros(0)).device
        for name, buf in self._buffers.items():
            if buf is not None:
                self._buffers[name] = buf.to(device)
        return self

    def forward(self, maps: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
        """The cues in float32, outside any autocast; returned in ``maps``' dtype."""
        with torch.autocast(maps.device.type, enabled=False):
            return self._cues(maps.float().contiguous(), light.float()).to(maps.dtype)

    def _cues(self, maps: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
        cov = self.material_coverage()
        painted = self.painted(maps, cov)
        out = [painted if "paint" in self.cues else maps]
        sun = light[:, :3] @ self.camera_to_world  # camera space, (N, 3)
        shaded = {"normal", "reflection", "glossy", "ambient", "shade"} & set(self.cues)
        normal = self.shading_normal(maps, cov) if shaded else None
        mirrored = {"reflection", "glossy", "ambient"} & set(self.cues)
        refl = self.reflection(normal) if mirrored else None  # once, for every cue that uses it
        vis = self.visibility(light[:, :3]) if {"shadow", "shade"} & set(self.cues) else None
        lit = {"glossy", "ambient", "shade"} & set(self.cues)
        surface = self.surface(painted) if lit else None  # decoded once for every such cue
        for cue in self.cues:
            if cue == "geometry":
                out.append(self.geometry_planes().expand(maps.shape[0], -1, -1, -1))
            elif cue == "light":
                planes = torch.cat([sun, light[:, 3:]], 1)[:, :, None, None]
                out.append(planes.expand(-1, -1, *maps.shape[-2:]))
            elif cue == "normal":
                out.append(normal)
            elif cue == "reflection":
                out.append(refl)
            elif cue == "shadow":
                out.append(vis)
            elif cue == "glossy":
                out.append(self.glossy(surface, refl, light))
            elif cue == "ambient":
                out.append(self.ambient(surface, normal, refl, light))
            elif cue == "shade":
                out.append(self.shade(surface, normal, vis, light))
        return torch.cat(out, 1)

    # ---- the cues ---------------------------------------------------------------------------

    def material_coverage(self) -> torch.Tensor:
        """``(1, 1, H, W)``: the pixel's coverage of the material."""
        return self.parts[MATERIAL_ROWS].sum(0)[None, None]

    def painted(self, maps: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
        """The maps with every other part's material added in its coverage: diffuse and
        specular as sRGB-encoded greys, roughness, and a flat normal (sky: all white)."""
        r = self.r
        m = self.part_materials  # (P, 3) linear diffuse, specular, roughness
        grey = srgb_encode(m[:, :2])
        half, one = torch.full_like(m[:, :1], 0.5), torch.ones_like(m[:, :1])  # a flat normal
        values = torch.cat(
            [grey[:, :1].expand(-1, 3), grey[:, 1:2].expand(-1, 3), m[:, 2:3].expand(-1, r),
             half, half, one], 1,
        )  # fmt: skip
        values[PARTS.index("sky")].fill_(1.0)
        fill = _mix(values[OTHER_ROWS].T, self.parts[OTHER_ROWS])
        return maps + fill[None]

    def geometry_planes(self) -> torch.Tensor:
        """``(1, 10, H, W)``: normal, inverse depth, part coverages."""
        depth = (-self.position[2:3]).clamp_min(0)
        inverse = torch.where(depth > 1e-3, 3.0 / depth.clamp_min(1e-3), torch.zeros_like(depth))
        return torch.cat([self.normal, inverse, self.parts])[None]

    def shading_normal(self, maps: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
        """``(N, 3, H, W)`` unit camera-space normals: the material's normal map (``maps``
        unpainted) in its tangent frame where the material is, the surface normal elsewhere,
        mixed by the material's coverage ``cov``."""
        k = 6 + self.r
        # the maps are the material's values weighted by its coverage: undo that first
        nmap = maps[:, k : k + 3] / cov.clamp_min(0.05) * 2 - 1
        tb = (self.tangent, self.bitangent, self.normal)
        mapped = sum(nmap[:, i : i + 1] * v[None] for i, v in enumerate(tb))
        n = cov * mapped + (1 - cov) * self.normal[None]
        return _unit(n, 1, eps=1e-6)

    def reflection(self, normal: torch.Tensor) -> torch.Tensor:
        """``(N, 3, H, W)``: the view direction mirrored about ``normal``, in world space."""
        view = -self.rays[None]
        r = 2 * (normal * view).sum(1, keepdim=True) * normal - view
        return _mix(self.camera_to_world, r)

    def visibility(self, sun_world: torch.Tensor) -> torch.Tensor:
        """``(N, 1, H, W)``: 1 where the sun is seen from the pixel's surface, else 0."""
        surface = (1 - self.parts[PARTS.index("sky")]).clamp_min(1e-6)
        p_cam = self.position / surface  # the surface's own position
        n_world = _unit(_mix(self.camera_to_world, self.normal), 0)
        p = _mix(self.camera_to_world, p_cam) + self.camera_location[:, None, None]
        origin = (p + RAY_OFFSET * n_world)[None]  # (1, 3, H, W)
        d = _unit(sun_world, 1)[:, :, None, None]  # (N, 3, 1, 1)
        blocked = torch.zeros((d.shape[0], 1, *p.shape[-2:]), dtype=torch.bool, device=p.device)
        # every caster of a kind at once (a handful of operations, not a handful a caster)
        for hits in (
            _sphere_blocks(origin, d, self.spheres),
            _frustum_blocks(origin, d, self.frustums),
        ):
            for hit in hits.unbind(0):
                blocked = blocked | hit
        return (~blocked).float()

    def surface(self, painted) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The painted maps' linear diffuse and specular ``(N, 3, H, W)`` and Blender's
        roughness ``r`` ``(N, 1, H, W)``: what the shading cues read."""
        colours = srgb_decode(painted[:, 0:6].clamp(0, 1))
        rough = painted[:, 6:7] if self.r == 1 else painted[:, 6:9].mean(1, keepdim=True)
        return colours[:, 0:3], colours[:, 3:6], rough

    def glossy(self, surface, refl, light) -> torch.Tensor:
        """``(N, 3, H, W)`` tonemapped radiance of the sky and the floor in the specular lobe,
        along the world-space reflection ``refl``."""
        return self.tonemap(self._glossy(surface, refl, *self._environment(light)))

    def ambient(self, surface, normal, refl, light) -> torch.Tensor:
        """``(N, 3, H, W)`` tonemapped radiance of every surface lit by the sky and the sun-lit
        floor, not by the sun: Lambert under the sky above and the floor below, plus
        :meth:`glossy`'s term."""
        diffuse = surface[0]
        up = self._up(normal)
        sky, floor = self._environment(light)
        below = (1 - up) / 2  # the share of the surface's hemisphere under the horizon
        irradiance = math.pi * (sky * (1 - below) + floor * below)
        radiance = diffuse / math.pi * irradiance * (1 - self.parts[PARTS.index("sky")])
        return self.tonemap(radiance + self._glossy(surface, refl, sky, floor))

    def _up(self, normal) -> torch.Tensor:
        """``(N, 1, H, W)``: the world's z of camera-space ``normal``."""
        return (normal * self.camera_to_world[2][None, :, None, None]).sum(1, keepdim=True)

    def _environment(self, light) -> tuple[float, torch.Tensor]:
        """The radiance of the sky (a uniform one of ``SKY_IRRADIANCE``) and, ``(N, 3, 1,
        1)``, of the floor lit by the sun and that sky (Lambert, no shadows)."""
        floor_albedo = self.part_materials[PARTS.index("floor"), 0]
        sun_z = _unit(light[:, :3], 1)[:, 2:3].clamp_min(0)
        floor = floor_albedo / math.pi * (sun_irradiance(light) * sun_z + SKY_IRRADIANCE)
        return SKY_IRRADIANCE / math.pi, floor[:, :, None, None]

    def _glossy(self, surface, refl, sky, floor) -> torch.Tensor:
        """:meth:`glossy`'s linear radiance, under the ``sky`` and ``floor`` of
        :meth:`_environment`."""
        _, specular, rough = surface
        up = refl[:, 2:3]
        sky_weight = (0.5 + 0.5 * up / (rough * rough).clamp_min(HORIZON_BLEND)).clamp(0, 1)
        arriving = sky_weight * sky + (1 - sky_weight) * floor
        albedo = 1 - GLOSSY_LOSS * rough
        return specular * albedo * arriving * (1 - self.parts[PARTS.index("sky")])

    def shade(self, surface, normal, vis, light) -> torch.Tensor:
        """``(N, 3, H, W)`` tonemapped radiance of the sun and a sky term on every surface."""
        diffuse, specular, rough = surface
        sun_cam = _unit(light[:, :3] @ self.camera_to_world, 1)[:, :, None, None]
        view = -self.rays[None]
        nl = (normal * sun_cam).sum(1, keepdim=True)
        nv = (normal * view).sum(1, keepdim=True).clamp_min(1e-4)
        lit = nl.clamp_min(0) * vis
        h = _unit(sun_cam + view, 1)
        nh = (normal * h).sum(1, keepdim=True).clamp(0, 1)
        alpha = (rough * rough).clamp_min(MIN_ALPHA)
        a2 = alpha * alpha
        d = a2 / (math.pi * (nh * nh * (a2 - 1) + 1) ** 2)
        g = _smith_g1(nl.clamp_min(1e-4), a2) * _smith_g1(nv, a2)
        brdf = diffuse / math.pi + specular * d * g / (4 * nl.clamp_min(1e-4) * nv)
        sun_rgb = sun_irradiance(light)[:, :, None, None]
        up = self._up(normal)
        sky = diffuse * SKY_IRRADIANCE / math.pi * (1 + up) / 2
        sky_cov = self.parts[PARTS.index("sky")]
        radiance = (brdf * sun_rgb * lit + sky) * (1 - sky_cov)
        return self.tonemap(radiance) + SKY_SHADE * sky_cov  # the sky itself is not shaded


def _unit(x: torch.Tensor, dim: int, eps: float = 1e-12) -> torch.Tensor:
    """``x`` scaled to unit length along ``dim``, as ``F.normalize(x, dim=dim, eps=eps)``.
    Written out: torch's vector norm reduces a dimension other than the innermost about a
    hundred times slower on the CPU than this sum of squares."""
    return x / (x * x).sum(dim, keepdim=True).sqrt().clamp_min(eps)


def _mix(m: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``m (O, C)`` applied to the channels of ``x (..., C, H, W)`` → ``(..., O, H, W)``: a
    matrix product (ONNX's oldest opsets have no Einsum)."""
    flat = x.flatten(-2)
    return (m @ flat).view(*x.shape[:-3], m.shape[0], *x.shape[-2:])


def _rays(n: int, tangent: float) -> torch.Tensor:
    """``(3, n, n) float32`` unit camera-space directions through the pixel centres."""
    return torch.from_numpy(camera_rays(n, tangent)).permute(2, 0, 1).float().contiguous()


def _smith_g1(x: torch.Tensor, a2: torch.Tensor) -> torch.Tensor:
    return 2 * x / (x + torch.sqrt(a2 + (1 - a2) * x * x))


def _sphere_blocks(o: torch.Tensor, d: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """``(K, N, 1, H, W)``: whether the rays ``o + t d`` (t > 0; ``o (1, 3, H, W)``,
    ``d (N, 3, 1, 1)``) meet each sphere of ``s (K, 9)`` (centre, radius, band axis, band lo
    and hi as fractions of the radius) outside its open band."""
    s = s[:, None, :, None, None]  # (K, 1, 9, 1, 1): a caster a row, then the rays' axes
    c, radius, axis, lo, hi = s[:, :, :3], s[:, :, 3:4], s[:, :, 4:7], s[:, :, 7:8], s[:, :, 8:9]
    o, d = o[None], d[None]
    oc = o - c
    b = (oc * d).sum(2, keepdim=True)
    cc = (oc * oc).sum(2, keepdim=True) - radius * radius
    disc = b * b - cc
    root = torch.sqrt(disc.clamp_min(0))
    hit = torch.zeros_like(disc, dtype=torch.bool)
    for t in (-b - root, -b + root):
        height = ((oc + t * d) * axis).sum(2, keepdim=True) / radius
        open_ = (height > lo) & (height < hi)
        hit = hit | ((disc > 0) & (t > 0) & ~open_)
    return hit


def _frustum_blocks(o: torch.Tensor, d: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """``(J, N, 1, H, W)``: whether the rays ``o + t d`` (t > 0; as :func:`_sphere_blocks`'s)
    meet each vertical frustum of ``f (J, 4)`` (z0, z1, r0, r1) about the world's z axis:
    its side or its caps."""
    f = f[:, None, :, None, None]  # (J, 1, 4, 1, 1)
    z0, z1, r0, r1 = f[:, :, 0:1], f[:, :, 1:2], f[:, :, 2:3], f[:, :, 3:4]
    k = (r1 - r0) / (z1 - z0)
    o, d = o[None], d[None]
    ox, oy, oz = o[:, :, 0:1], o[:, :, 1:2], o[:, :, 2:3]
    dx, dy, dz = d[:, :, 0:1], d[:, :, 1:2], d[:, :, 2:3]
    rad0 = r0 + k * (oz - z0)  # the radius at the origin's height
    a = dx * dx + dy * dy - (k * dz) ** 2
    b = 2 * (ox * dx + oy * dy - rad0 * k * dz)
    c = ox * ox + oy * oy - rad0 * rad0
    disc = b * b - 4 * a * c
    root = torch.sqrt(disc.clamp_min(0))
    safe = torch.where(a.abs() < 1e-9, torch.full_like(a, 1e-9), a)
    hit = torch.zeros_like(disc + oz, dtype=torch.bool)
    for t in ((-b - root) / (2 * safe), (-b + root) / (2 * safe)):
        z = oz + t * dz
        radius = r0 + k * (z - z0)
        hit = hit | ((disc > 0) & (t > 0) & (z >= z0) & (z <= z1) & (radius > 0))
    for zc, rc in ((z0, r0), (z1, r1)):
        t = (zc - oz) / torch.where(dz.abs() < 1e-9, torch.full_like(dz, 1e-9), dz)
        x, y = ox + t * dx, oy + t * dy
        hit = hit | ((t > 0) & (x * x + y * y <= rc * rc))
    return hit


#: the wavelengths (µm) of the sun lamp's red, green and blue, and their Rayleigh optical depths
LAMBDA = (0.680, 0.550, 0.440)
RAYLEIGH = tuple(0.008569 * lam**-4 * (1 + 0.0113 * lam**-2 + 0.00013 * lam**-4) for lam in LAMBDA)


def sun_irradiance(light: torch.Tensor) -> torch.Tensor:
    """``(N, 3)`` linear RGB irradiance of the sun lamp for light vectors ``(N, 4)``: the
    torch form of :func:`render_jobs.sun.sun_lamp` (strength x colour)."""
    z = _unit(light[:, :3], 1)[:, 2].clamp(-1, 1)
    zenith = 90.0 - torch.asin(z) * (180.0 / math.pi)  # degrees
    cosz = torch.cos(zenith * (math.pi / 180.0))
    mass = 1.0 / (cosz + 0.50572 * (96.07995 - zenith).clamp_min(1e-3) ** -1.6364)
    turbidity = light[:, 3:4] * TURBIDITY_SCALE
    beta = (0.04608 * turbidity - 0.04586).clamp_min(0)
    # a column a wavelength, from Python numbers (the module docstring: no host data)
    columns = zip(LAMBDA, RAYLEIGH, strict=True)
    depth = torch.cat([rayleigh + beta * lam**-1.3 for lam, rayleigh in columns], 1)
    t = torch.exp(-mass[:, None] * depth)
    strength = sunlib.SUN_ZENITH_IRRADIANCE * t[:, 1:2] / float(sunlib.transmittance(90.0, 2.0)[1])
    return strength * t / t.amax(1, keepdim=True)
