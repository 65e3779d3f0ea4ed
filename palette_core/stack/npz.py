"""Weight stacks in one NPZ file (format ``palette-weights/1``).

The file loads with ``numpy.load(path, allow_pickle=False)``; ``read_npz_stack``
validates every key and names what is wrong.
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from ..basis import Basis, check_basis
from ..errors import InputError
from .base import FORMAT, WeightStack, check_dtype, check_meta, check_names

#: Most that deflate can expand its input (a 258-byte match from about two bits): the
#: largest array a deflated member of n bytes can hold is about n times this.
MAX_DEFLATE_RATIO = 1032


def write_npz_stack(stack: WeightStack, file: str | os.PathLike, dtype: str | None = None) -> None:
    """Write ``stack`` as NPZ format v1 to ``file`` (a path or a binary file object).

    ``dtype`` (float32 or float16) converts the weights; None keeps the first image's.
    """
    dtype = str(stack.weights[0].dtype) if dtype is None else dtype
    check_dtype(dtype)
    arrays = {
        "format": np.array(FORMAT),
        "palette": np.asarray(stack.palette, np.float32),
        "basis": np.array(str(stack.basis)),
        "order": np.array(stack.order, np.int64),
        "names": np.array(stack.names, dtype=str),
        "method": np.array(stack.method),
        "meta": np.array(json.dumps(stack.meta)),
    }
    if stack.basis == Basis.ADDITIVE:
        arrays["hull_faces"] = np.asarray(stack.hull_faces, np.int32).reshape(-1, 3)
    shapes = {w.shape for w in stack.weights}
    if len(shapes) == 1:
        arrays["weights"] = np.stack([w.astype(dtype, copy=False) for w in stack.weights])
    else:
        for i, w in enumerate(stack.weights):
            arrays[f"weights_{i:04d}"] = w.astype(dtype, copy=False)
    np.savez(file, **arrays)


def read_npz_stack(path: str | os.PathLike) -> WeightStack:
    """Read and validate an NPZ weight stack.

    Only the keys of the format are read, and each array's declared shape is
    checked against its stored size before it is loaded, so a crafted file can
    neither make us allocate what it does not hold nor load members we do not use.

    Raises
    ------
    InputError
        If the file is missing, not an NPZ, or any key is absent or malformed
        (the message names the key): names must be distinct relative paths,
        weights finite, the palette in [0, 1].
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"weight stack {path} does not exist")
    with NpzReader(path, f"a {FORMAT} stack") as npz:
        if npz.text("format") != FORMAT:
            raise InputError(f"{path}: format is {npz.text('format')!r}, expected {FORMAT!r}")
        palette = npz.array("palette", "f")
        if palette.ndim != 2 or palette.shape[1] != 3 or len(palette) == 0:
            raise InputError(f"{path}: palette must have shape (K, 3), got {palette.shape}")
        if not np.isfinite(palette).all() or palette.min() < 0 or palette.max() > 1:
            raise InputError(f"{path}: palette values must lie in [0, 1]")
        try:
            basis = Basis.parse(npz.text("basis"))
        except InputError as exc:
            raise InputError(f"{path}: {exc}") from None
        order = npz.array("order", "iu")
        if order.ndim != 0:
            raise InputError(f"{path}: order must be an integer >= 1, got {order}")
        order = int(order)
        m = check_basis(len(palette), basis, order, str(path))
        names = npz.array("names", "U")
        if names.ndim != 1:
            raise InputError(f"{path}: names must be a 1-D array of strings")
        names = names.tolist()
        check_names(names, str(path))
        if "weights" in npz:
            stacked = npz.array("weights", "f")
            if stacked.ndim != 4:
                raise InputError(f"{path}: weights must have shape (N, H, W, M), "
                                 f"got {stacked.shape}")
            weights = list(stacked)
        else:
            weights = [npz.array(f"weights_{i:04d}", "f") for i in range(len(names))]
        if len(weights) != len(names):
            raise InputError(f"{path}: {len(names)} names but {len(weights)} weight images")
        for name, w in zip(names, weights):
            if w.ndim != 3 or w.shape[2] != m or w.dtype not in (np.float32, np.float16):
                raise InputError(f"{path}: weights of {name} must be float32/float16 of shape "
                                 f"(H, W, {m}), got {w.dtype} {w.shape}")
            if not np.isfinite(w).all():
                raise InputError(f"{path}: weights of {name} hold NaN or infinity")
        hull_faces = np.zeros((0, 3), np.int32)
        if basis == Basis.ADDITIVE and "hull_faces" in npz:
            hull_faces = npz.array("hull_faces", "iu")
            if hull_faces.ndim != 2 or hull_faces.shape[1] != 3:
                raise InputError(f"{path}: hull_faces must be integers of shape (F, 3)")
            if hull_faces.size and (hull_faces.min() < 0 or hull_faces.max() >= len(palette)):
                raise InputError(f"{path}: hull_faces index outside the palette")
        meta = npz.json("meta") if "meta" in npz else {}
        check_meta(meta, names, str(path))
        method = npz.text("method")
    return WeightStack(palette.astype(np.float32), weights, names, method, basis, order,
                       hull_faces.astype(np.int32), meta)


class NpzReader:
    """The arrays of an NPZ file, read one key at a time, never unpickled.

    Nothing a file declares is trusted before it is checked against what the file holds:
    a member's compressed bytes must lie inside the file, its uncompressed size (which the
    zip directory states) can be at most what those bytes expand to (``MAX_DEFLATE_RATIO``)
    and at most this machine's memory, and the ``.npy`` header's shape and dtype must
    account for exactly that size, all before any array is allocated.
    """

    def __init__(self, path: Path, what: str):
        self.path, self.what = path, what

    def __enter__(self) -> NpzReader:
        try:
            self.zip = zipfile.ZipFile(self.path)
            self.size = os.fstat(self.zip.fp.fileno()).st_size
        except (OSError, zipfile.BadZipFile, ValueError) as exc:
            raise InputError(f"{self.path} is not a readable NPZ file ({self.what}): "
                             f"{exc}") from None
        self.members = {name[:-4]: name for name in self.zip.namelist() if name.endswith(".npy")}
        return self

    def __exit__(self, *exc) -> None:
        self.zip.close()

    def __contains__(self, key: str) -> bool:
        return key in self.members

    def array(self, key: str, kinds: str) -> np.ndarray:
        """The array ``key``, whose dtype kind must be one of ``kinds`` ('f', 'iu', 'U')."""
        if key not in self.members:
            raise InputError(f"{self.path}: missing key {key!r} (is it {self.what}?)")
        info = self.zip.getinfo(self.members[key])
        self._check_sizes(key, info)
        try:
            with self.zip.open(info) as f:
                version = np.lib.format.read_magic(f)
                read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                               else np.lib.format.read_array_header_2_0)
                shape, _, dtype = read_header(f)
                header = f.tell()
                if dtype.kind not in kinds or dtype.hasobject:
                    raise InputError(f"{self.path}: key {key!r} has dtype {dtype}")
                declared = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
                if declared != info.file_size - header:
                    raise InputError(f"{self.path}: key {key!r} declares shape {shape} "
                                     "but holds another size")
            with self.zip.open(info) as f:
                return np.lib.format.read_array(f, allow_pickle=False)
        except (OSError, ValueError, EOFError, RuntimeError, zipfile.BadZipFile,
                zlib.error) as exc:
            raise InputError(f"{self.path}: key {key!r} cannot be read: {exc}") from None

    def _check_sizes(self, key: str, info: zipfile.ZipInfo) -> None:
        """InputError unless member ``key`` may hold the size its directory entry states."""
        ratio = {zipfile.ZIP_STORED: 1, zipfile.ZIP_DEFLATED: MAX_DEFLATE_RATIO}
        if info.flag_bits & 0x1:
            raise InputError(f"{self.path}: key {key!r} is encrypted (NPZ files are not)")
        if info.compress_type not in ratio:
            raise InputError(f"{self.path}: key {key!r} is compressed with method "
                             f"{info.compress_type} (NPZ files are stored or deflated)")
        if (info.header_offset + info.compress_size > self.size
                or info.file_size > ratio[info.compress_type] * info.compress_size + 64):
            # (+ 64: deflate's few bytes of framing around a tiny member)
            raise InputError(f"{self.path}: key {key!r} states {info.file_size} bytes, more "
                             f"than its {info.compress_size} bytes in the file can hold")
        if info.file_size > memory_bytes():
            raise InputError(f"{self.path}: key {key!r} states {info.file_size} bytes, more "
                             "than this machine's memory")

    def text(self, key: str) -> str:
        value = self.array(key, "U")
        if value.ndim != 0:
            raise InputError(f"{self.path}: key {key!r} must be a string")
        return str(value)

    def json(self, key: str):
        try:
            return json.loads(self.text(key))
        except (json.JSONDecodeError, RecursionError) as exc:
            raise InputError(f"{self.path}: {key} is not valid JSON: {exc}") from None


def memory_bytes() -> int:
    """This machine's physical memory in bytes: no array we read can be larger."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
