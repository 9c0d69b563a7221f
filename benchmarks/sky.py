"""Sun/sky balance: horizontal irradiance of the Sun lamp vs the Hosek-Wilkie sky, measured
on the ground plane of the real scene, for a few suns.

    .venv/bin/python -m benchmarks.sky       # about a minute on 2 cores

The ground (albedo 0.35) right of the ball is lit by sun and sky; rendering it once more with
the lamp switched off gives the sky alone: E_sky = L_ground * pi / albedo. The lamp's own
horizontal irradiance is its strength x sin(elevation). This process is a Blender worker: it
imports bpy itself and leaves with os._exit (see render_jobs.blender).
"""

from __future__ import annotations

import math
import os
import sys
import tempfile

from render_jobs.materials.uniform import uniform_maps
from render_jobs.specs import RenderSettings, UniformValues
from render_jobs.sun import sun_from_angles, sun_lamp


def main() -> None:
    os.environ["SHADERBALL_BLENDER_WORKER"] = "1"
    from render_jobs.blender import sky as sky_module
    from render_jobs.blender.renderer import ShaderballRenderer

    albedo = 0.35  # the ground's (render_jobs.blender.renderer)
    renderer = ShaderballRenderer(
        RenderSettings(resolution=96, samples=64), tempfile.mkdtemp(prefix="bench-sky-")
    )
    renderer.set_material(uniform_maps(UniformValues((0.5,) * 3, (0.1,) * 3, 0.5)))
    print(f"{'elevation':>9}{'turbidity':>10}{'E_sun':>8}{'E_sky':>8}{'sun/sky':>9}")
    for elevation, turbidity in [(80, 2), (60, 3), (40, 3), (20, 6)]:
        sun = sun_from_angles(elevation, 0, turbidity)  # sun at +X: the right side is lit
        sky_module.sun_lamp = lambda _sun: (0.0, (1.0, 1.0, 1.0))  # lamp off: sky alone
        render, _ = renderer.render(sun, 3)
        sky_module.sun_lamp = sun_lamp
        ground = float(render.radiance.mean(0)[88:94, 80:94].mean())
        e_sky = ground * math.pi / albedo
        e_sun = sun_lamp(sun)[0] * math.sin(math.radians(elevation))
        print(f"{elevation:>9}{turbidity:>10}{e_sun:>8.3f}{e_sky:>8.3f}{e_sun / e_sky:>9.1f}")
    sys.stdout.flush()
    os._exit(0)  # bpy deadlocks at normal interpreter exit


if __name__ == "__main__":
    main()
