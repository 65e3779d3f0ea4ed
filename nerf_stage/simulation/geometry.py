"""Flatten a parsed scene into the arrays the path-tracing kernel reads.

Spheres, quads, triangles, discs and open cylinders are the primitives; a box
becomes six quads, a cylinder its side and two discs, a mesh its triangles, an
area light an emitting quad. Each object's primitives share one bounding box that
rays test first.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from palette_core.basis import Basis, n_terms, transport_terms

from .pathtracer import CYLINDER, DISC, QUAD, SPHERE, TRIANGLE
from .scene import Scene

PRIM_WIDTH = 18
BOX_PAD = 1e-6


class SceneArrays(NamedTuple):
    """Geometry, materials and lights as flat arrays; the kernel ``pathtracer.trace_view`` takes
    the record whole (numba reads named tuples of arrays)."""

    prim_kind: np.ndarray  # (P,) int64
    prim_data: np.ndarray  # (P, 18)
    prim_mat: np.ndarray  # (P,) int64
    groups: np.ndarray  # (G, 8) bounding box, first and end primitive
    mat_albedo: np.ndarray  # (Mt, 3)
    mat_texture: np.ndarray  # (Mt,) int64, -1 without texture
    mat_tex_scale: np.ndarray  # (Mt, 2)
    mat_palette: np.ndarray  # (Mt,) int64 palette index, -1 for fixed
    mat_emission: np.ndarray  # (Mt, 3)
    tex_info: np.ndarray  # (T, 3) int64 offset, height, width
    tex_pixels: np.ndarray  # (texels, 3)
    area_lights: np.ndarray  # (La, 16)
    point_lights: np.ndarray  # (Lp, 6)


def next_term_table(k: int, order: int) -> np.ndarray:
    """(M, K) int64: index of term ``terms[m] + (i,)`` in the transport basis, -1 past ``order``.

    Examples
    --------
    >>> next_term_table(2, 1).tolist()  # terms (), (0,), (1,)
    [[1, 2], [-1, -1], [-1, -1]]
    """
    terms = transport_terms(k, order)
    index = {term: m for m, term in enumerate(terms)}
    table = np.full((n_terms(k, Basis.TRANSPORT, order), max(k, 1)), -1, np.int64)
    for m, term in enumerate(terms):
        for i in range(k):
            table[m, i] = index.get(tuple(sorted(term + (i,))), -1)
    return table


def scene_arrays(scene: Scene) -> SceneArrays:
    """Flatten ``scene`` for ``pathtracer.trace_view``."""
    prims: list[tuple[int, np.ndarray, int]] = []
    groups = []
    for obj in scene.objects:
        first = len(prims)
        prims += [(kind, data, obj["material"]) for kind, data in _primitives(obj)]
        groups.append((first, len(prims)))

    n_materials = len(scene.materials)
    area_lights, point_lights, emission = [], [], []
    for light in scene.lights:
        if light["type"] == "point":
            point_lights.append(np.concatenate([light["position"], light["intensity"]]))
            continue
        corner, e1, e2 = light["corner"], light["edge1"], light["edge2"]
        normal = np.cross(e1, e2)
        area = np.linalg.norm(normal)
        area_lights.append(np.concatenate([corner, e1, e2, normal / area, [area],
                                           light["emission"]]))
        first = len(prims)
        prims.append((QUAD, _quad(corner, e1, e2), n_materials + len(emission)))
        emission.append(light["emission"])
        groups.append((first, len(prims)))

    prim_data = np.zeros((len(prims), PRIM_WIDTH))
    for i, (_, data, _) in enumerate(prims):
        prim_data[i, : len(data)] = data
    prim_kind = np.array([p[0] for p in prims], np.int64)
    boxes = np.array([_bounds(kind, data) for kind, data in zip(prim_kind, prim_data)])
    group_rows = [np.concatenate([boxes[a:b, 0].min(0) - BOX_PAD, boxes[a:b, 1].max(0) + BOX_PAD,
                                  [a, b]]) for a, b in groups if b > a]

    # lights become black, untextured, fixed materials that emit
    materials = scene.materials
    textures = [m.texture for m in materials if m.texture is not None]
    tex_offsets = np.cumsum([0] + [t.shape[0] * t.shape[1] for t in textures])
    tex_ids = np.cumsum([m.texture is not None for m in materials]) - 1
    n_lights = len(emission)
    return SceneArrays(
        prim_kind=prim_kind,
        prim_data=prim_data,
        prim_mat=np.array([p[2] for p in prims], np.int64),
        groups=np.array(group_rows, np.float64).reshape(-1, 8),
        mat_albedo=np.array([m.albedo for m in materials] + [np.zeros(3)] * n_lights),
        mat_texture=np.array([t if m.texture is not None else -1
                              for m, t in zip(materials, tex_ids)] + [-1] * n_lights, np.int64),
        mat_tex_scale=np.array([m.texture_scale for m in materials] + [(1.0, 1.0)] * n_lights),
        mat_palette=np.array([scene.palette_index(m) for m in materials] + [-1] * n_lights,
                             np.int64),
        mat_emission=np.array([np.zeros(3)] * n_materials + emission),
        tex_info=np.array([(o, t.shape[0], t.shape[1]) for o, t in zip(tex_offsets, textures)],
                          np.int64).reshape(-1, 3),
        tex_pixels=(np.concatenate([t.reshape(-1, 3) for t in textures]) if textures
                    else np.zeros((1, 3))).astype(np.float64),
        area_lights=np.array(area_lights, np.float64).reshape(-1, 16),
        point_lights=np.array(point_lights, np.float64).reshape(-1, 6),
    )


def _primitives(obj: dict) -> list[tuple[int, np.ndarray]]:
    """(kind, data) rows of one object."""
    kind = obj["type"]
    if kind == "sphere":
        return [(SPHERE, np.concatenate([obj["center"], [obj["radius"]]]))]
    if kind == "quad":
        return [(QUAD, _quad(obj["corner"], obj["edge1"], obj["edge2"]))]
    if kind == "box":
        rot = _rotation_y(obj["rotate_y"])
        half = obj["size"] / 2
        faces = []
        for axis in range(3):
            e1, e2 = np.eye(3)[(axis + 1) % 3], np.eye(3)[(axis + 2) % 3]
            for side in (-1.0, 1.0):
                corner = -half + (side > 0) * np.eye(3)[axis] * obj["size"]
                faces.append((QUAD, _quad(obj["center"] + rot @ corner,
                                          rot @ (e1 * obj["size"]), rot @ (e2 * obj["size"]))))
        return faces
    if kind == "cylinder":
        axis = obj["axis"] / np.linalg.norm(obj["axis"])
        tangent = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
        tangent /= np.linalg.norm(tangent)
        prims = [(CYLINDER, np.concatenate([obj["base"], axis, [obj["radius"], obj["height"]],
                                            tangent]))]
        if obj["caps"]:
            top = obj["base"] + obj["height"] * axis
            for centre, normal in ((obj["base"], -axis), (top, axis)):
                prims.append((DISC, np.concatenate([centre, normal, [obj["radius"]], tangent])))
        return prims
    mesh = obj["path"]  # a trimesh.Trimesh
    vertices = (mesh.vertices * obj["scale"]) @ _rotation_y(obj["rotate_y"]).T + obj["translate"]
    uv = getattr(mesh.visual, "uv", None)
    uv = np.zeros((len(vertices), 2)) if uv is None or len(uv) != len(vertices) else uv
    prims = []
    for face in mesh.faces:
        v0, v1, v2 = vertices[face]
        normal = np.cross(v1 - v0, v2 - v0)
        length = np.linalg.norm(normal)
        if length == 0:  # degenerate triangles are invisible anyway
            continue
        prims.append((TRIANGLE, np.concatenate([v0, v1 - v0, v2 - v0, normal / length,
                                                uv[face].ravel()])))
    return prims


def _quad(corner, e1, e2) -> np.ndarray:
    """Corner, edges, unit normal and the dual vector w = n / |n|^2 (n = e1 x e2)."""
    n = np.cross(e1, e2)
    return np.concatenate([corner, e1, e2, n / np.linalg.norm(n), n / n.dot(n)])


def _rotation_y(degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _bounds(kind: int, d: np.ndarray) -> np.ndarray:
    """(2, 3) axis-aligned bounds of one primitive."""
    if kind == SPHERE:
        points = np.array([d[:3] - d[3], d[:3] + d[3]])
    elif kind in (QUAD, TRIANGLE):
        points = d[:3] + np.array([[0, 0], [1, 0], [0, 1], [1, 1]]) @ d[3:9].reshape(2, 3)
        if kind == TRIANGLE:
            points = points[:3]
    elif kind == DISC:
        points = np.array([d[:3] - d[6], d[:3] + d[6]])
    else:  # CYLINDER
        ends = np.array([d[:3], d[:3] + d[7] * d[3:6]])
        points = np.concatenate([ends - d[6], ends + d[6]])
    return np.array([points.min(0), points.max(0)])
