"""What the Blender scene scripts share: materials, cameras, and writing a Blender-layout
dataset: training views, held-out views on the training path (``val``) and off it
(``test``), and both held-out splits rendered again under another sampler seed
(``val_seed2/``, ``test_seed2/``: the noise floor).

A scene script builds its scene with ``bpy`` and calls ``render_dataset`` with its camera
poses; run it as ``blender -b --factory-startup -P SCRIPT -- OUTDIR [--resolution N]
[--views TRAIN VAL TEST] [--spp N]``.
"""

import argparse
import json
import math
import sys
from pathlib import Path

import bpy
from mathutils import Matrix, Vector


def parse(views=(100, 8, 8)) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog=Path(sys.argv[-1]).name)
    parser.add_argument("outdir", type=Path)
    parser.add_argument("--resolution", type=int, default=100)
    parser.add_argument("--views", type=int, nargs=3, default=views,
                        metavar=("TRAIN", "VAL", "TEST"))
    parser.add_argument("--spp", type=int, default=64)
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    return parser.parse_args(argv)


def empty_scene(fov_degrees: float = 50.0, transparent: bool = False):
    """A new scene with a camera, rendered by Cycles on the CPU without denoising."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    bpy.ops.object.camera_add()
    scene.camera = bpy.context.object
    scene.camera.data.angle = math.radians(fov_degrees)
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.use_denoising = False
    scene.render.film_transparent = transparent
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    scene.view_settings.view_transform = "Standard"
    return scene


def material(name, colour, roughness=0.6, metallic=0.0, texture=None):
    """A principled material; ``texture`` = (node type, scale, other colour) mixes a
    procedural pattern into its base colour."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*colour, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Metallic"].default_value = metallic
    if texture is not None:
        kind, scale, other = texture
        pattern = nodes.new(kind)
        pattern.inputs["Scale"].default_value = scale
        mix = nodes.new("ShaderNodeMixRGB")
        mix.inputs["Color1"].default_value = (*colour, 1.0)
        mix.inputs["Color2"].default_value = (*other, 1.0)
        factor = pattern.outputs["Fac"] if "Fac" in pattern.outputs else pattern.outputs[0]
        links.new(factor, mix.inputs["Fac"])
        links.new(mix.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def add(mesh_operator, mat, **kwargs):
    """Add a primitive (``bpy.ops.mesh.primitive_*_add``) with one material."""
    mesh_operator(**kwargs)
    bpy.context.object.data.materials.append(mat)
    return bpy.context.object


def sky(strength=0.6, sun=(0.4, 0.3, 0.8)):
    world = bpy.data.worlds.new("sky")
    bpy.context.scene.world = world
    world.use_nodes = True
    texture = world.node_tree.nodes.new("ShaderNodeTexSky")
    texture.sky_type = "HOSEK_WILKIE"
    texture.sun_direction = sun
    background = world.node_tree.nodes["Background"]
    world.node_tree.links.new(texture.outputs["Color"], background.inputs["Color"])
    background.inputs["Strength"].default_value = strength


def look_at(eye, target) -> Matrix:
    """Camera-to-world matrix (OpenGL axes, as Blender's cameras) at ``eye`` facing
    ``target`` with +z up."""
    eye, target = Vector(eye), Vector(target)
    forward = (target - eye).normalized()
    right = forward.cross(Vector((0, 0, 1))).normalized()
    up = right.cross(forward)
    return Matrix.Translation(eye) @ Matrix((right, up, -forward)).transposed().to_4x4()


def _render(folder: Path, matrices, seed: int) -> list:
    scene = bpy.context.scene
    scene.cycles.seed = seed
    frames = []
    for i, matrix in enumerate(matrices):
        scene.camera.matrix_world = matrix
        scene.render.filepath = str(folder / f"r_{i:03d}.png")
        bpy.ops.render.render(write_still=True)
        frames.append({"file_path": f"./{folder.name}/r_{i:03d}",
                       "transform_matrix": [list(row) for row in matrix]})
        print(f"{folder.name}: {i + 1}/{len(matrices)}", flush=True)
    return frames


def render_dataset(args, train_poses, val_poses, test_poses) -> None:
    """Render the three splits (seed 0) as a Blender-layout dataset in ``args.outdir``, and
    the held-out ones again under seed 1 into ``val_seed2/`` and ``test_seed2/``."""
    scene = bpy.context.scene
    scene.render.resolution_x = scene.render.resolution_y = args.resolution
    scene.render.resolution_percentage = 100
    scene.cycles.samples = args.spp
    for split, poses in (("train", train_poses), ("val", val_poses), ("test", test_poses)):
        frames = _render(args.outdir / split, poses, seed=0)
        data = {"camera_angle_x": scene.camera.data.angle, "frames": frames}
        (args.outdir / f"transforms_{split}.json").write_text(json.dumps(data, indent=1))
        if split != "train":
            _render(args.outdir / f"{split}_seed2", poses, seed=1)
