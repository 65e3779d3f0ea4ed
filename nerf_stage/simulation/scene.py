"""Scene descriptions: JSON or TOML files, and the built-in scenes.

A scene file holds five sections (docs/simulation.md documents every field)::

    materials  name -> {"albedo": [r, g, b] | "texture": "skimage:coffee" | "img.png",
                        "texture_scale": [su, sv], "editable": bool}
               | {"colour_of": name}
    objects    [{"type": "sphere" | "quad" | "box" | "cylinder" | "mesh", "material": name, ...}]
    lights     [{"type": "area", "corner", "edge1", "edge2", "emission"}
                | {"type": "point", "position", "intensity"}]
    camera     {"rig": "orbit" | "hemisphere" | "front-arc", "target", "radius",
                "elevation", "arc", "fov", "resolution",
                "views": {"train", "val", "test", "off_ring"}}
    render     {"light": "direct" | "indirect", "order", "max_depth", "spp", "seed"}

Editable materials are the palette, in the order they are listed; their albedos
are plain colours. A material with ``colour_of`` takes another editable material's palette
colour: two objects of one colour whose materials can still be told apart (to re-simulate
an edit of one of them only, ``simulate.with_palette``). Files are read and checked by
``scene_file``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

BUILTIN_SCENES = ("cornell-box", "still-life", "room-corner", "marbles", "open-field",
                  "forward-shelf", "clay-twins")
#: The primitives of ``objects[]``: each type's fields and their kinds (``_Fields``), the
#: one table a new primitive's parsing takes (geometry.py and pathtracer.py draw it).
OBJECT_FIELDS = {
    "sphere": {"center": "vector", "radius": "positive"},
    "quad": {"corner": "vector", "edge1": "vector", "edge2": "vector"},
    "box": {"center": "vector", "size": "vector", "rotate_y": "number"},
    "cylinder": {"base": "vector", "axis": "vector", "radius": "positive", "height": "positive",
                 "caps": "bool"},
    "mesh": {"path": "path", "scale": "positive", "translate": "vector", "rotate_y": "number"},
}
OBJECT_TYPES = tuple(OBJECT_FIELDS)
#: Defaults of the object fields a scene may leave out.
OPTIONAL_FIELDS = {"rotate_y": 0.0, "axis": [0.0, 1.0, 0.0], "caps": True, "scale": 1.0,
                   "translate": [0.0, 0.0, 0.0]}
LIGHT_TYPES = ("area", "point")
RIGS = ("orbit", "hemisphere", "front-arc")
SPLITS = ("train", "val", "test")
SKIMAGE_PREFIX = "skimage:"
# scikit-image samples shipped inside the wheel (others would need a download)
SKIMAGE_TEXTURES = ("astronaut", "brick", "camera", "chelsea", "coffee", "grass", "gravel",
                    "moon", "rocket")

#: Inclusive ranges of the integer settings, checked before any work (scene files and
#: command-line overrides alike): beyond them a simulation would not fit in memory or time.
LIMITS = {"resolution": (1, 4096), "views": (0, 100_000), "spp": (1, 1 << 16),
          "order": (0, 8), "max_depth": (1, 64), "seed": (0, 2**63 - 1)}

#: Largest per-term radiance buffer of one simulation (views x pixels x terms x 3 float64).
MAX_TERM_BYTES = 8 << 30


@dataclass
class Material:
    """A diffuse material."""

    name: str
    albedo: np.ndarray  # (3,) float64; white when a texture gives the colour
    texture: np.ndarray | None = None  # (H, W, 3) float64 in [0, 1]
    texture_scale: tuple[float, float] = (1.0, 1.0)
    editable: bool = False
    colour_of: str | None = None  # the editable material whose palette colour this one shares


@dataclass
class Camera:
    """Where the views are taken from and how they are imaged."""

    rig: str
    target: np.ndarray  # (3,) the point every camera looks at
    radius: float  # distance from the target
    elevation: tuple[float, float]  # degrees above the target's horizontal plane
    arc: float  # degrees of azimuth covered (front-arc) around +z
    fov: float  # horizontal field of view, degrees
    width: int
    height: int
    views: dict[str, int]  # views per split
    off_ring: int = 0  # test views away from the rig (``cameras.off_ring_poses``)


@dataclass
class RenderSettings:
    """Which light transport is simulated, and how many samples."""

    light: str  # "direct" (one surface vertex) or "indirect"
    order: int  # transport order n kept in the weights
    max_depth: int  # surface vertices per path
    spp: int
    seed: int


@dataclass
class Scene:
    """A parsed, validated scene. Objects and lights stay dicts of floats for ``geometry.py``."""

    name: str
    materials: list[Material]
    objects: list[dict]
    lights: list[dict]
    camera: Camera
    render: RenderSettings
    source: dict = field(repr=False, default_factory=dict)  # the file's contents

    @property
    def palette_materials(self) -> list[Material]:
        """The editable materials that own a palette colour, in palette order."""
        return [m for m in self.materials if m.editable and m.colour_of is None]

    def palette_index(self, material: Material) -> int:
        """The palette colour ``material`` takes (its own, or its ``colour_of``'s); -1 for a
        fixed material."""
        names = [m.name for m in self.palette_materials]
        name = material.colour_of or material.name
        return names.index(name) if material.editable else -1


def builtin_scene_path(name: str) -> Path:
    """Path of the JSON file of built-in scene ``name``."""
    return Path(str(resources.files("nerf_stage.simulation") / "scenes" / f"{name}.json"))
