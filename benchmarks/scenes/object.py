"""An object with a transparent background, in the NeRF-synthetic layout: a glossy teapot-like
stack (a metallic sphere on a textured cylinder, a matte cone beside it) on a small glossy
plinth, lit by a sun and the sky but rendered on transparent film. Training views cover the
upper hemisphere on a spiral; val views lie on that spiral between training views, test
views off it (closer, at other elevations and azimuths).

    blender -b --factory-startup -P benchmarks/scenes/object.py -- OUTDIR
"""

import math
import sys
from pathlib import Path

import bpy

sys.path.insert(0, str(Path(__file__).parent))
from _common import add, empty_scene, look_at, material, parse, render_dataset, sky  # noqa: E402

TARGET = (0.0, 0.0, 0.45)


def build() -> None:
    empty_scene(40.0, transparent=True)
    mesh = bpy.ops.mesh
    add(mesh.primitive_cylinder_add, material("plinth", (0.85, 0.85, 0.82), 0.25),
        radius=0.8, depth=0.1, location=(0, 0, 0.05))
    add(mesh.primitive_cylinder_add, material(
        "textured", (0.80, 0.30, 0.10), 0.6,
        texture=("ShaderNodeTexWave", 8.0, (0.95, 0.85, 0.55))),
        radius=0.28, depth=0.5, location=(-0.15, 0.1, 0.35), vertices=48)
    bpy.ops.object.shade_smooth()
    add(mesh.primitive_uv_sphere_add, material("metal", (0.2, 0.35, 0.8), 0.2, metallic=1.0),
        radius=0.22, location=(-0.15, 0.1, 0.82), segments=48, ring_count=24)
    bpy.ops.object.shade_smooth()
    add(mesh.primitive_cone_add, material("matte", (0.2, 0.6, 0.25), 0.9),
        radius1=0.2, depth=0.45, location=(0.35, -0.2, 0.32), vertices=48)
    sky(strength=0.8)
    bpy.ops.object.light_add(type="SUN", rotation=(math.radians(35), 0, math.radians(-40)))
    bpy.context.object.data.energy = 3.0


def hemisphere(n: int, radius: float, elevations, phase: float) -> list:
    """``n`` views on a spiral over the upper hemisphere between two elevations (degrees)."""
    poses = []
    for i in range(n):
        low, high = elevations
        elevation = math.radians(low + (high - low) * i / max(n - 1, 1))
        azimuth = 2 * math.pi * (i * 0.618034 + phase)
        eye = (radius * math.cos(elevation) * math.cos(azimuth),
               radius * math.cos(elevation) * math.sin(azimuth),
               TARGET[2] + radius * math.sin(elevation))
        poses.append(look_at(eye, TARGET))
    return poses


def main() -> None:
    args = parse()
    build()
    train, val, test = args.views
    spiral = hemisphere(2 * train, 3.2, (10, 70), 0.0)  # every other view is held out
    render_dataset(args, spiral[::2], spiral[1::2][::max(1, train // val)][:val],
                   hemisphere(test, 2.8, (20, 55), 0.31))


main()
