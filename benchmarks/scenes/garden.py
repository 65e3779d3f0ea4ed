"""An unbounded outdoor scene: a glossy sphere, a textured cube and a matte torus on a
textured ground that reaches the horizon under a sky, with blocks far outside the cameras'
ring. Training views circle the objects at one radius with a height that waves; val views
lie on that path between training views, test views off it (closer, higher).

    blender -b --factory-startup -P benchmarks/scenes/garden.py -- OUTDIR
"""

import math
import sys
from pathlib import Path

import bpy

sys.path.insert(0, str(Path(__file__).parent))
from _common import add, empty_scene, look_at, material, parse, render_dataset, sky  # noqa: E402

TARGET = (0.0, 0.0, 0.6)


def build() -> None:
    empty_scene(50.0)
    mesh = bpy.ops.mesh
    add(mesh.primitive_plane_add, material(
        "ground", (0.30, 0.42, 0.18), 0.9,
        texture=("ShaderNodeTexChecker", 40.0, (0.55, 0.48, 0.30))), size=400.0)
    add(mesh.primitive_uv_sphere_add, material("glossy", (0.75, 0.08, 0.06), 0.12),
        radius=0.5, location=(0.6, 0.3, 0.5), segments=64, ring_count=32)
    bpy.ops.object.shade_smooth()
    add(mesh.primitive_cube_add, material(
        "textured", (0.95, 0.80, 0.20), 0.5,
        texture=("ShaderNodeTexChecker", 6.0, (0.15, 0.25, 0.70))),
        size=0.7, location=(-0.6, 0.4, 0.35), rotation=(0, 0, math.radians(30)))
    add(mesh.primitive_torus_add, material("matte", (0.15, 0.55, 0.75), 0.8),
        location=(0.0, -0.7, 0.25), major_radius=0.35, minor_radius=0.12)
    for i in range(8):  # blocks far outside the ring
        angle, distance = 2 * math.pi * i / 8 + 0.3, 12.0 + 10.0 * (i % 3)
        block = add(mesh.primitive_cube_add, material(f"far{i}", (0.6, 0.35 + 0.05 * i, 0.3)),
                    size=1.0, location=(distance * math.cos(angle), distance * math.sin(angle),
                                        1.0))
        block.scale = (1.0 + i % 2 * 3.0, 1.0, 2.0)
    sky()
    bpy.ops.object.light_add(type="SUN", rotation=(math.radians(40), 0, math.radians(35)))
    bpy.context.object.data.energy = 3.0


def main() -> None:
    args = parse()
    build()
    train, val, test = args.views

    def ring(angles):
        return [look_at((4 * math.cos(a), 4 * math.sin(a), 1.3 + 0.4 * math.sin(3 * a)),
                        TARGET) for a in angles]

    off = [look_at((3 * math.cos(a), 3 * math.sin(a), 2.3), TARGET)
           for a in (2 * math.pi * (i + 0.37) / test for i in range(test))]
    render_dataset(args, ring(2 * math.pi * i / train for i in range(train)),
                   ring(2 * math.pi * (i * train // val + 0.5) / train for i in range(val)),
                   off)


main()
