"""PLY splat files: the 3D Gaussian splatting layout (``x y z``, ``f_dc_*``, ``f_rest_*``,
``opacity``, ``scale_*``, ``rot_*``; any property order, float or double, other properties
kept) read and written here, and SuperSplat's compressed PLY (chunks of 256 splats
quantised between their bounds) through PyPI's ``gsply``.

The header is parsed and the body's size checked against what it declares before anything
is read, so a count that lies allocates nothing.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from palette_core.errors import InputError

from .fields import (
    REST_COEFFICIENTS,
    SplatFields,
    as_fields,
    from_gsdata,
    gsply_module,
    unit_quaternions,
)

#: numpy's scalar types by the names of PLY 1.0, and those names by type and by alias.
NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
         "f4": "float", "f8": "double"}
TYPES = {**{name: kind for kind, name in NAMES.items()},
         **{f"{base}{8 * int(kind[1])}": kind for kind, base in
            (("i1", "int"), ("u1", "uint"), ("i2", "int"), ("u2", "uint"), ("i4", "int"),
             ("u4", "uint"), ("f4", "float"), ("f8", "float"))}}
ENDIAN = {"binary_little_endian": "<", "binary_big_endian": ">"}
MAX_HEADER_LINES = 10_000
#: The properties every 3D Gaussian splatting vertex has.
SPLAT_PROPERTIES = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0",
                    "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
#: SuperSplat's compressed PLY: its elements' names.
COMPRESSED_ELEMENTS = ("chunk", "vertex")


@dataclass
class Element:
    """One element of a PLY header: its ``name``, ``count`` and (name, dtype) properties."""

    name: str
    count: int
    properties: list[tuple[str, str]]

    @property
    def row_bytes(self) -> int:
        return sum(np.dtype(kind).itemsize for _, kind in self.properties)


@dataclass
class Header:
    """A binary PLY's header: byte order, elements, comments and where the body starts."""

    endian: str
    elements: list[Element]
    comments: list[str]
    body: int

    def element(self, name: str) -> Element | None:
        return next((e for e in self.elements if e.name == name), None)


def read_header(path: Path) -> Header:
    """The header of the binary PLY at ``path``, its body's size checked against it.

    Raises
    ------
    InputError
        If it is not a binary PLY of scalar properties, or the body is not exactly what the
        elements declare (truncated, or a count that lies).
    """
    with open(path, "rb") as file:
        if file.read(4) != b"ply\n":
            raise InputError(f"{path} is not a PLY file")
        lines = []
        while not lines or lines[-1] != "end_header":
            if len(lines) >= MAX_HEADER_LINES:
                raise InputError(f"{path}: the PLY header does not end")
            line = file.readline(4096)
            if not line.endswith(b"\n"):
                raise InputError(f"{path}: the PLY header is cut short")
            lines.append(line.decode("ascii", "replace").strip())
        body = file.tell()
    endian, elements, comments = None, [], []
    for line in lines[:-1]:
        words = line.split()
        if not words:
            continue
        if words[0] == "format":
            if len(words) < 2 or words[1] not in ENDIAN:
                raise InputError(f"{path}: a PLY in format {' '.join(words[1:2])} is not read: "
                                 "write it as binary_little_endian")
            endian = ENDIAN[words[1]]
        elif words[0] in ("comment", "obj_info"):
            comments.append(line.partition(" ")[2])
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append(Element(words[1], int(words[2]), []))
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in TYPES:
            elements[-1].properties.append((words[2], endian_type(endian, words[1])))
        else:
            raise InputError(f"{path}: the PLY header line {line[:60]!r} is not one of a "
                             "splat file (list properties are not read)")
    if endian is None:
        raise InputError(f"{path}: the PLY header names no format")
    declared = sum(e.count * e.row_bytes for e in elements)
    size = path.stat().st_size - body
    if declared != size:
        raise InputError(f"{path}: the PLY header declares {declared} bytes of data, the file "
                         f"holds {size}: it is truncated or its counts are wrong")
    return Header(endian, elements, comments, body)


def endian_type(endian: str | None, name: str) -> str:
    return (endian or "<") + TYPES[name]


def read_tables(path: Path, header: Header) -> dict[str, np.ndarray]:
    """Each element of ``header`` as a structured array, read from the body."""
    tables, offset = {}, header.body
    for element in header.elements:
        dtype = np.dtype(element.properties)
        tables[element.name] = np.fromfile(path, dtype, element.count, offset=offset)
        offset += element.count * element.row_bytes
    return tables


def read_ply(path: str | os.PathLike) -> SplatFields:
    """The splats of a 3D Gaussian splatting PLY or of SuperSplat's compressed PLY."""
    path = Path(path)
    header = read_header(path)
    names = [e.name for e in header.elements]
    if names[:2] == list(COMPRESSED_ELEMENTS):
        return _read_compressed(path, header)
    vertex = header.element("vertex")
    present = {name for name, _ in vertex.properties} if vertex else set()
    missing = [name for name in SPLAT_PROPERTIES if name not in present]
    if missing:
        raise InputError(f"{path} is a PLY but not of splats: its vertices lack "
                         f"{', '.join(missing[:4])}")
    table = _vertices(path, header, vertex)
    rest = sorted((n for n in present if n.startswith("f_rest_")), key=lambda n: int(n[7:]))
    if len(rest) // 3 not in REST_COEFFICIENTS.values() or len(rest) % 3 or rest != [
            f"f_rest_{i}" for i in range(len(rest))]:
        raise InputError(f"{path}: {len(rest)} f_rest properties are not the spherical "
                         "harmonics of degree 1, 2 or 3")
    s = vertex.count
    shN = (table(*rest).reshape(s, 3, -1).transpose(0, 2, 1) if rest  # noqa: N806
           else np.zeros((s, 0, 3)))
    known = set(SPLAT_PROPERTIES) | set(rest)
    return as_fields(table("x", "y", "z"), table("f_dc_0", "f_dc_1", "f_dc_2"), shN,
                     table("opacity")[:, 0], table("scale_0", "scale_1", "scale_2"),
                     table("rot_0", "rot_1", "rot_2", "rot_3"), comments=header.comments,
                     extras={n: table(n)[:, 0].copy() for n, _ in vertex.properties
                             if n not in known})


def _vertices(path: Path, header: Header, vertex: Element):
    """A reader of (S, n) columns of the vertex element by name: from one float32 matrix
    when every property is a little-endian float (the common file), else from its
    structured table."""
    if all(kind == "<f4" for _, kind in vertex.properties) and header.elements[0] is vertex:
        matrix = np.fromfile(path, "<f4", vertex.count * len(vertex.properties),
                             offset=header.body).reshape(vertex.count, -1)
        index = {name: i for i, (name, _) in enumerate(vertex.properties)}
        return lambda *names: matrix[:, [index[n] for n in names]]
    structured = read_tables(path, header)["vertex"]
    return lambda *names: np.stack([structured[n] for n in names], 1)


def _read_compressed(path: Path, header: Header) -> SplatFields:
    """SuperSplat's compressed PLY, through ``gsply`` (its chunk count checked first)."""
    chunk, vertex = header.element("chunk"), header.element("vertex")
    if chunk.count != -(-vertex.count // 256):
        raise InputError(f"{path}: a compressed PLY of {vertex.count} splats has "
                         f"{chunk.count} chunks, not one per 256")
    gsply = gsply_module("compressed PLY")
    data = gsply.reader.read_compressed(path)
    if data is None:
        raise InputError(f"{path} is a compressed PLY of a variant gsply does not read")
    return from_gsdata(data, comments=header.comments)


def write_ply(fields: SplatFields, path: str | os.PathLike) -> None:
    """``fields`` as a binary little-endian 3D Gaussian splatting PLY: x, y, z, f_dc_*,
    f_rest_* (channel by channel, as 3D Gaussian splatting flattens them), opacity,
    scale_*, rot_*, then the ``extras``; the ``comments`` in the header."""
    s = len(fields)
    rest = fields.shN.transpose(0, 2, 1).reshape(s, -1)
    columns = {
        **{axis: fields.means[:, i] for i, axis in enumerate("xyz")},
        **{f"f_dc_{i}": fields.sh0[:, i] for i in range(3)},
        **{f"f_rest_{i}": column for i, column in enumerate(rest.T)},
        "opacity": fields.opacities,
        **{f"scale_{i}": fields.scales[:, i] for i in range(3)},
        **{f"rot_{i}": fields.quats[:, i] for i in range(4)},
    }
    names = [*columns, *fields.extras]
    if all(value.dtype == np.float32 for value in fields.extras.values()):
        table = np.concatenate([fields.means, fields.sh0, rest, fields.opacities[:, None],
                                fields.scales, fields.quats,
                                *[v[:, None] for v in fields.extras.values()]], 1).astype("<f4")
        kinds = ["float"] * len(names)
    else:
        table = np.empty(s, [(name, "<f4") for name in columns] + [
            (name, value.dtype.newbyteorder("<")) for name, value in fields.extras.items()])
        for name, value in {**columns, **fields.extras}.items():
            table[name] = value
        kinds = [NAMES[table.dtype[n].str[1:]] for n in names]
    header = ("ply\nformat binary_little_endian 1.0\n"
              + "".join(f"comment {c}\n" for c in fields.comments)
              + f"element vertex {s}\n"
              + "".join(f"property {kind} {name}\n" for kind, name in zip(kinds, names))
              + "end_header\n")
    with open(path, "wb") as file:
        file.write(header.encode("ascii"))
        table.tofile(file)


def write_compressed_ply(fields: SplatFields, path: str | os.PathLike) -> None:
    """``fields`` as SuperSplat's compressed PLY, through ``gsply`` (positions, scales and
    colours quantised per chunk of 256 splats, rotations as smallest three)."""
    gsply = gsply_module("compressed PLY")
    gsply.writer.write_compressed(Path(path), fields.means, fields.scales,
                                  unit_quaternions(fields.quats), fields.opacities, fields.sh0,
                                  fields.shN if fields.shN.shape[1] else None)
