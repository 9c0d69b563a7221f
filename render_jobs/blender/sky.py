"""The Hosek-Wilkie sky and its sun lamp: the only code that names the sky model.

bpy 4.5 LTS keeps ``sky_type='HOSEK_WILKIE'`` (5.x marks it legacy); should it change, it
changes here. The sky texture has no sun disc, so a Sun lamp in the same direction carries
the direct light, with strength and colour from ``render_jobs.sun.sun_lamp``.

The world's importance map is rebuilt whenever the sky changes (every sun): at Cycles'
default 1024 px it costs more than a small render, and the sky is smooth (the sun is the lamp),
so it is built at ``WORLD_MAP_RESOLUTION``.
"""

from __future__ import annotations

import math

from render_jobs.blender.bpy_guard import bpy, mathutils
from render_jobs.specs import Sun
from render_jobs.sun import SUN_ANGLE_DEG, sun_lamp

SKY_MODEL = "HOSEK_WILKIE"
GROUND_ALBEDO = 0.3
WORLD_MAP_RESOLUTION = 256


class SkyAndSun:
    """The world (sky) and the Sun lamp of one scene; :meth:`set_sun` changes both."""

    def __init__(self, scene):
        world = bpy.data.worlds.new("sky")
        world.use_nodes = True
        nodes, links = world.node_tree.nodes, world.node_tree.links
        nodes.clear()
        self.sky = nodes.new("ShaderNodeTexSky")
        self.sky.sky_type = SKY_MODEL
        self.sky.ground_albedo = GROUND_ALBEDO
        background = nodes.new("ShaderNodeBackground")
        background.inputs["Strength"].default_value = 1.0
        out = nodes.new("ShaderNodeOutputWorld")
        links.new(self.sky.outputs["Color"], background.inputs["Color"])
        links.new(background.outputs["Background"], out.inputs["Surface"])
        world.cycles.sampling_method = "MANUAL"
        world.cycles.sample_map_resolution = WORLD_MAP_RESOLUTION
        scene.world = world
        light = bpy.data.lights.new("sun", "SUN")
        light.angle = math.radians(SUN_ANGLE_DEG)
        self.lamp = bpy.data.objects.new("sun", light)
        scene.collection.objects.link(self.lamp)

    def set_sun(self, sun: Sun) -> None:
        """Point sky and lamp at ``sun`` and set turbidity, lamp strength and colour."""
        direction = mathutils.Vector(sun.direction)
        self.sky.sun_direction = direction
        self.sky.turbidity = sun.turbidity
        strength, colour = sun_lamp(sun)
        self.lamp.data.energy = strength
        self.lamp.data.color = colour
        # a Sun lamp shines along its local -Z: point +Z at the sun
        self.lamp.rotation_euler = direction.to_track_quat("Z", "Y").to_euler()
