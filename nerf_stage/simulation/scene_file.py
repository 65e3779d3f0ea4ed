"""Scene files read and checked: every message about a malformed file names the field
(docs/simulation.md documents every field)."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import numpy as np
import skimage.data
import trimesh

from palette_core.errors import InputError
from palette_core.io import load_image

from .scene import (
    BUILTIN_SCENES,
    LIGHT_TYPES,
    LIMITS,
    OBJECT_FIELDS,
    OBJECT_TYPES,
    OPTIONAL_FIELDS,
    RIGS,
    SKIMAGE_PREFIX,
    SKIMAGE_TEXTURES,
    SPLITS,
    Camera,
    Material,
    RenderSettings,
    Scene,
    builtin_scene_path,
)


def load_scene(spec: str) -> Scene:
    """Load a built-in scene by name, or a scene file (``.json`` or ``.toml``).

    Raises
    ------
    InputError
        Unknown name (the message lists the built-ins), unreadable file, or a
        malformed field (the message names it).
    """
    path = Path(spec)
    if spec in BUILTIN_SCENES:
        path = builtin_scene_path(spec)
    elif path.suffix.lower() not in (".json", ".toml"):
        raise InputError(f"unknown scene {spec!r}: give a built-in scene "
                         f"({', '.join(BUILTIN_SCENES)}) or a .json / .toml scene file")
    if not path.is_file():
        raise InputError(f"scene file {path} does not exist")
    try:
        text = path.read_text()
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, tomllib.TOMLDecodeError,
            RecursionError) as exc:
        raise InputError(f"scene file {path} cannot be parsed: {exc}") from None
    return parse_scene(data, name=spec if spec in BUILTIN_SCENES else path.stem, root=path.parent)


def parse_scene(data: dict, name: str = "scene", root: Path = Path(".")) -> Scene:
    """Validate a scene dictionary; relative texture and mesh paths resolve against ``root``."""
    reader = _Fields(name)
    top = reader.table(data, "scene")
    materials = _parse_materials(reader, reader.table(top.get("materials"), "materials"), root)
    names = [m.name for m in materials]
    objects = [_parse_object(reader, obj, f"objects[{i}]", names, root)
               for i, obj in enumerate(reader.list(top.get("objects"), "objects"))]
    lights = [_parse_light(reader, light, f"lights[{i}]")
              for i, light in enumerate(reader.list(top.get("lights", []), "lights", empty=True))]
    if not lights:
        raise InputError(f"scene {name}: field 'lights' must hold at least one light")
    camera = _parse_camera(reader, reader.table(top.get("camera"), "camera"))
    render = _parse_render(reader, reader.table(top.get("render", {}), "render"))
    unknown = set(top) - {"materials", "objects", "lights", "camera", "render"}
    if unknown:
        raise InputError(f"scene {name}: unknown field {sorted(unknown)[0]!r}")
    scene = Scene(name, materials, objects, lights, camera, render, source=data)
    if render.light == "indirect" and not scene.palette_materials:
        raise InputError(f"scene {name}: indirect light sorts paths by editable material, "
                         "but no material is marked \"editable\": true")
    return scene


class _Fields:
    """Typed field readers whose errors name the scene and the field."""

    def __init__(self, scene: str):
        self.scene = scene

    def fail(self, where: str, expected: str, got) -> InputError:
        return InputError(f"scene {self.scene}: field {where!r} must be {expected}, got {got!r}")

    def table(self, value, where: str) -> dict:
        if not isinstance(value, dict):
            raise self.fail(where, "a table of fields", value)
        return value

    def list(self, value, where: str, empty: bool = False) -> list:
        if not isinstance(value, list) or not (value or empty):
            raise self.fail(where, "a non-empty list", value)
        return value

    def number(self, value, where: str, low=-np.inf, high=np.inf, inclusive=True) -> float:
        ok = (isinstance(value, (int, float)) and not isinstance(value, bool)
              and math.isfinite(value))
        if ok:
            ok = low <= value <= high if inclusive else low < value < high
        if not ok:
            brackets = "[]" if inclusive else "()"
            bounds = f" in {brackets[0]}{low}, {high}{brackets[1]}"
            raise self.fail(where, "a number" + ("" if np.isinf([low, high]).all() else bounds),
                            value)
        return float(value)

    def integer(self, value, where: str, limit: str) -> int:
        low, high = LIMITS[limit]
        if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
            raise self.fail(where, f"an integer in [{low}, {high}]", value)
        return value

    def vector(self, value, where: str) -> np.ndarray:
        if (not isinstance(value, list) or len(value) != 3
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                           and math.isfinite(v) for v in value)):
            raise self.fail(where, "a list of 3 finite numbers", value)
        return np.array(value, np.float64)

    def colour(self, value, where: str, high=1.0) -> np.ndarray:
        """A colour [r, g, b] (or one number for grey) with channels in [0, high]."""
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            value = [value] * 3
        rgb = self.vector(value, where)
        if not (rgb >= 0).all() or not (rgb <= high).all():
            raise self.fail(where, f"a colour with channels in [0, {high}]", value)
        return rgb

    def choice(self, value, where: str, choices) -> str:
        if value not in choices:
            raise self.fail(where, "one of " + ", ".join(choices), value)
        return value

    def only(self, table: dict, where: str, allowed) -> None:
        unknown = set(table) - set(allowed)
        if unknown:
            raise InputError(f"scene {self.scene}: unknown field {where}.{sorted(unknown)[0]}")


def _parse_materials(reader: _Fields, table: dict, root: Path) -> list[Material]:
    materials = []
    for name, spec in table.items():
        where = f"materials.{name}"
        spec = reader.table(spec, where)
        if "colour_of" in spec:
            materials.append(_shared_colour(reader, name, spec, where, materials))
            continue
        reader.only(spec, where, ("albedo", "texture", "texture_scale", "editable"))
        editable = spec.get("editable", False)
        if not isinstance(editable, bool):
            raise reader.fail(f"{where}.editable", "true or false", editable)
        if ("albedo" in spec) == ("texture" in spec):
            raise reader.fail(where, "given exactly one of 'albedo' and 'texture'", sorted(spec))
        if "albedo" in spec:
            materials.append(Material(name, reader.colour(spec["albedo"], f"{where}.albedo"),
                                      editable=editable))
            continue
        if editable:
            raise reader.fail(f"{where}.editable", "false for a textured material (the "
                              "palette holds plain albedos)", editable)
        scale = spec.get("texture_scale", [1.0, 1.0])
        if not isinstance(scale, list) or len(scale) != 2:
            raise reader.fail(f"{where}.texture_scale", "a list of 2 positive numbers", scale)
        scale = tuple(reader.number(s, f"{where}.texture_scale", 0, np.inf, False) for s in scale)
        texture = _load_texture(reader, spec["texture"], f"{where}.texture", root)
        materials.append(Material(name, np.ones(3), texture, scale))
    if not materials:
        raise reader.fail("materials", "a non-empty table", table)
    return materials


def _shared_colour(reader: _Fields, name: str, spec: dict, where: str,
                   before: list[Material]) -> Material:
    """A material whose colour is that of an editable material listed before it."""
    reader.only(spec, where, ("colour_of",))
    owners = {m.name: m for m in before if m.editable and m.colour_of is None}
    owner = owners.get(spec["colour_of"]) if isinstance(spec["colour_of"], str) else None
    if owner is None:
        raise reader.fail(f"{where}.colour_of", "the name of an editable material with an "
                          "albedo listed before it", spec["colour_of"])
    return Material(name, owner.albedo, editable=True, colour_of=owner.name)


def _load_texture(reader: _Fields, spec, where: str, root: Path) -> np.ndarray:
    """(H, W, 3) float64 albedo in [0, 1] from a scikit-image sample or an image file."""
    if not isinstance(spec, str):
        raise reader.fail(where, "an image path or 'skimage:NAME'", spec)
    if spec.startswith(SKIMAGE_PREFIX):
        sample = spec[len(SKIMAGE_PREFIX):]
        if sample not in SKIMAGE_TEXTURES:
            raise reader.fail(where, "skimage:NAME with NAME one of " + ", ".join(SKIMAGE_TEXTURES),
                              spec)
        pixels = np.asarray(getattr(skimage.data, sample)())
        if pixels.ndim == 2:
            pixels = np.repeat(pixels[..., None], 3, axis=2)
        return pixels[..., :3] / float(np.iinfo(pixels.dtype).max)
    path = Path(spec) if Path(spec).is_absolute() else root / spec
    try:
        return load_image(path).rgb
    except InputError as exc:
        raise InputError(f"scene {reader.scene}: field {where!r}: {exc}") from None


def _parse_object(reader: _Fields, obj, where: str, materials: list[str], root: Path) -> dict:
    obj = reader.table(obj, where)
    kind = reader.choice(obj.get("type"), f"{where}.type", OBJECT_TYPES)
    fields = OBJECT_FIELDS[kind]
    reader.only(obj, where, ("type", "material", *fields))
    parsed = {"type": kind, "material": materials.index(
        reader.choice(obj.get("material"), f"{where}.material", materials))}
    for key, kind_of in fields.items():
        value = obj.get(key, OPTIONAL_FIELDS.get(key))
        if value is None:
            raise InputError(f"scene {reader.scene}: field {where}.{key} is missing")
        at = f"{where}.{key}"
        if kind_of == "vector":
            parsed[key] = reader.vector(value, at)
        elif kind_of == "positive":
            parsed[key] = reader.number(value, at, 0, np.inf, inclusive=False)
        elif kind_of == "number":
            parsed[key] = reader.number(value, at)
        elif kind_of == "bool":
            if not isinstance(value, bool):
                raise reader.fail(at, "true or false", value)
            parsed[key] = value
        else:
            parsed[key] = _load_mesh(reader, value, at, root)
    if kind == "box" and not (parsed["size"] > 0).all():
        raise reader.fail(f"{where}.size", "3 positive numbers", obj["size"])
    if kind == "cylinder" and np.linalg.norm(parsed["axis"]) == 0:
        raise reader.fail(f"{where}.axis", "a non-zero vector", obj["axis"])
    if kind == "quad" and np.linalg.norm(np.cross(parsed["edge1"], parsed["edge2"])) == 0:
        raise reader.fail(f"{where}.edge2", "an edge not parallel to edge1", obj["edge2"])
    return parsed


def _load_mesh(reader: _Fields, spec, where: str, root: Path) -> trimesh.Trimesh:
    if not isinstance(spec, str):
        raise reader.fail(where, "a mesh file path", spec)
    path = Path(spec) if Path(spec).is_absolute() else root / spec
    if not path.is_file():
        raise InputError(f"scene {reader.scene}: field {where!r}: mesh file {path} does not exist")
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as exc:  # trimesh raises many kinds on unreadable files
        raise InputError(f"scene {reader.scene}: field {where!r}: cannot read {path}: "
                         f"{exc}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"scene {reader.scene}: field {where!r}: {path} holds no triangles")
    return mesh


def _parse_light(reader: _Fields, light, where: str) -> dict:
    light = reader.table(light, where)
    kind = reader.choice(light.get("type"), f"{where}.type", LIGHT_TYPES)
    if kind == "area":
        reader.only(light, where, ("type", "corner", "edge1", "edge2", "emission"))
        parsed = {key: reader.vector(light.get(key), f"{where}.{key}")
                  for key in ("corner", "edge1", "edge2")}
        if np.linalg.norm(np.cross(parsed["edge1"], parsed["edge2"])) == 0:
            raise reader.fail(f"{where}.edge2", "an edge not parallel to edge1", light["edge2"])
        parsed["emission"] = reader.colour(light.get("emission"), f"{where}.emission", np.inf)
    else:
        reader.only(light, where, ("type", "position", "intensity"))
        parsed = {"position": reader.vector(light.get("position"), f"{where}.position"),
                  "intensity": reader.colour(light.get("intensity"), f"{where}.intensity", np.inf)}
    return {"type": kind, **parsed}


def _parse_camera(reader: _Fields, cam: dict) -> Camera:
    reader.only(cam, "camera", ("rig", "target", "radius", "elevation", "arc", "fov",
                                "resolution", "views"))
    rig = reader.choice(cam.get("rig"), "camera.rig", RIGS)
    elevation = cam.get("elevation", 30.0)
    if not isinstance(elevation, list):
        elevation = [elevation, elevation]
    if len(elevation) != 2:
        raise reader.fail("camera.elevation", "degrees or [low, high] degrees", elevation)
    low, high = (reader.number(e, "camera.elevation", -89.0, 89.0) for e in elevation)
    if low > high:
        raise reader.fail("camera.elevation", "[low, high] with low <= high", elevation)
    resolution = cam.get("resolution", 64)
    if not isinstance(resolution, list):
        resolution = [resolution, resolution]
    if len(resolution) != 2:
        raise reader.fail("camera.resolution", "an integer or [width, height]", resolution)
    width, height = (reader.integer(r, "camera.resolution", "resolution") for r in resolution)
    views = reader.table(cam.get("views", {"train": 100, "val": 10, "test": 20}), "camera.views")
    reader.only(views, "camera.views", (*SPLITS, "off_ring"))
    counts = {split: reader.integer(views.get(split, 0), f"camera.views.{split}", "views")
              for split in SPLITS}
    if counts["train"] < 1:
        raise reader.fail("camera.views.train", "an integer >= 1", views.get("train"))
    return Camera(
        rig=rig,
        target=reader.vector(cam.get("target", [0.0, 0.0, 0.0]), "camera.target"),
        radius=reader.number(cam.get("radius"), "camera.radius", 0, np.inf, inclusive=False),
        elevation=(low, high),
        arc=reader.number(cam.get("arc", 60.0), "camera.arc", 0, 360),
        fov=reader.number(cam.get("fov", 40.0), "camera.fov", 0, 180, inclusive=False),
        width=width, height=height, views=counts,
        off_ring=reader.integer(views.get("off_ring", 0), "camera.views.off_ring", "views"),
    )


def _parse_render(reader: _Fields, render: dict) -> RenderSettings:
    reader.only(render, "render", ("light", "order", "max_depth", "spp", "seed"))
    light = reader.choice(render.get("light", "direct"), "render.light", ("direct", "indirect"))
    if light == "direct":
        for key in ("order", "max_depth"):
            if key in render:
                raise InputError(f"scene {reader.scene}: field render.{key} needs "
                                 "render.light = \"indirect\"")
        order, max_depth = 1, 1
    else:
        order = reader.integer(render.get("order", 2), "render.order", "order")
        max_depth = reader.integer(render.get("max_depth", max(order, 1) + 2),
                                   "render.max_depth", "max_depth")
    return RenderSettings(
        light=light, order=order, max_depth=max_depth,
        spp=reader.integer(render.get("spp", 64), "render.spp", "spp"),
        seed=reader.integer(render.get("seed", 0), "render.seed", "seed"),
    )
