"""A forward-facing scene (the LLFF kind): objects on a table in front of a textured wall and
an open doorway onto a far sky, seen by cameras on a small grid that all face forward. Val
views lie in the grid's plane between training views, test views in front of it.

    blender -b --factory-startup -P benchmarks/scenes/forward.py -- OUTDIR
"""

import math
import sys
from pathlib import Path

import bpy

sys.path.insert(0, str(Path(__file__).parent))
from _common import add, empty_scene, look_at, material, parse, render_dataset, sky  # noqa: E402


def build() -> None:
    empty_scene(55.0)
    mesh = bpy.ops.mesh
    add(mesh.primitive_cube_add, material(
        "table", (0.55, 0.35, 0.20), 0.4,
        texture=("ShaderNodeTexWave", 3.0, (0.40, 0.22, 0.12))),
        size=1.0, location=(0, 0, -0.05), scale=(3.0, 2.0, 0.1))
    add(mesh.primitive_cube_add, material(
        "wall", (0.85, 0.82, 0.75), 0.8,
        texture=("ShaderNodeTexBrick", 4.0, (0.65, 0.30, 0.25))),
        size=1.0, location=(-1.6, -3.0, 1.5), scale=(3.0, 0.1, 4.0))
    add(mesh.primitive_cube_add, material("wall2", (0.85, 0.82, 0.75), 0.8),
        size=1.0, location=(2.6, -3.0, 1.5), scale=(3.0, 0.1, 4.0))
    add(mesh.primitive_uv_sphere_add, material("glossy", (0.9, 0.75, 0.1), 0.1),
        radius=0.3, location=(-0.5, 0.0, 0.3), segments=48, ring_count=24)
    bpy.ops.object.shade_smooth()
    add(mesh.primitive_cube_add, material(
        "textured", (0.2, 0.4, 0.8), 0.5,
        texture=("ShaderNodeTexChecker", 5.0, (0.9, 0.9, 0.9))),
        size=0.45, location=(0.4, -0.4, 0.225), rotation=(0, 0, math.radians(20)))
    add(mesh.primitive_cylinder_add, material("matte", (0.75, 0.2, 0.35), 0.9),
        radius=0.15, depth=0.7, location=(0.9, 0.3, 0.35), vertices=40)
    for i in range(5):  # far trees through the doorway
        add(mesh.primitive_cone_add, material(f"tree{i}", (0.1, 0.35 + 0.05 * i, 0.15)),
            radius1=1.0, depth=4.0, location=(0.3 + 3.0 * (i - 2), -15.0 - 4.0 * i, 1.5))
    add(mesh.primitive_plane_add, material("grass", (0.35, 0.45, 0.2), 0.9), size=300.0,
        location=(0, 0, -0.1))
    sky(strength=0.7, sun=(0.2, -0.6, 0.7))
    bpy.ops.object.light_add(type="SUN", rotation=(math.radians(30), 0, math.radians(160)))
    bpy.context.object.data.energy = 3.0


def grid(n: int, spread: float, depth: float) -> list:
    """``n`` forward-facing views on a grid about ``spread`` wide, ``depth`` from the table."""
    columns = math.ceil(math.sqrt(n * 1.5))
    rows = math.ceil(n / columns)
    poses = []
    for i in range(n):
        x = spread * ((i % columns) / max(columns - 1, 1) - 0.5)
        z = 1.0 + 0.6 * spread * ((i // columns) / max(rows - 1, 1) - 0.5)
        eye = (x, depth, z)
        poses.append(look_at(eye, (x * 0.3, -3.0, 0.6)))
    return poses


def main() -> None:
    args = parse()
    build()
    train, val, test = args.views
    test_poses = [look_at((x, 2.6, z), (x * 0.3, -3.0, 0.6)) for x, z in
                  ((-0.55, 0.85), (0.35, 1.2), (0.0, 1.0), (0.6, 0.8), (-0.2, 1.3), (0.2, 0.7),
                   (-0.7, 1.1), (0.75, 1.25), (-0.35, 0.75), (0.45, 1.0), (0.1, 1.15),
                   (-0.1, 0.9))[:test]]
    between = grid(train + val, 1.8, 3.0)  # every few views of a finer grid are held out
    held = set(range(1, train + val, (train + val) // val)[:val])
    render_dataset(args, [p for i, p in enumerate(between) if i not in held],
                   [between[i] for i in sorted(held)], test_poses)


main()
