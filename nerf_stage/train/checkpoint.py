"""A run's checkpoint (``checkpoint.pt``, docs/formats.md): written atomically, read as data.

A checkpoint from elsewhere is checked as strictly as a weight stack before anything is
computed from it: it is loaded with ``torch.load(weights_only=True)`` (tensors and plain
values only, so it cannot run code), its zip archive may not declare more bytes than the
file holds, and every tensor must be a dense tensor of a plain dtype that holds the values
it declares (a view repeating one row cannot stand for a billion), so that what a command
then allocates is a small multiple of the file's size.
"""

from __future__ import annotations

import warnings
import zipfile
from pathlib import Path

import torch

from palette_core.errors import InputError, first_line
from palette_core.outputs import atomic_outputs

CHECKPOINT = "checkpoint.pt"
#: What every checkpoint holds (a backbone adds its own keys).
KEYS = ("iteration", "config", "field", "output", "optimisers", "generator", "box",
        "intrinsics", "palette", "basis", "order", "meta", "log")
#: The dtypes a checkpoint's tensors may have.
DTYPES = frozenset({torch.float16, torch.bfloat16, torch.float32, torch.float64, torch.bool,
                    torch.uint8, torch.int8, torch.int16, torch.int32, torch.int64})
#: Bytes all tensors may declare together, per byte of the file (views of one storage count
#: each time), beyond ``DECLARED_SLACK``.
DECLARED_PER_BYTE = 4
DECLARED_SLACK = 1 << 20
#: Deepest nesting of lists and dicts looked into.
MAX_DEPTH = 32


def write_checkpoint(run, path: Path, model: dict, output: dict, optimisers: list,
                     generator: torch.Generator, extra: dict) -> None:
    """Write ``run``'s (a ``run.RunBase``) checkpoint atomically: its ``model``'s tensors (as
    ``field``), what it outputs, its optimisers' states and random state, what every run
    records, and the backbone's ``extra`` keys (docs/formats.md)."""
    record = run.record
    state = {
        "iteration": record.iteration,
        "config": run.config.to_dict(),
        "field": model,
        "output": output,
        "optimisers": optimisers,
        "generator": generator.get_state(),
        "box": run.box.to_dict(),
        "intrinsics": run.intrinsics.__dict__,
        "palette": run.palette.tolist(),
        "basis": str(run.basis),
        "order": run.order,
        "meta": {"dataset": record.dataset, "weights": record.weights,
                 "channels": record.channels, "stack_meta": record.stack_meta,
                 "frames_outside": record.frames_outside, "downscale": record.downscale},
        "log": record.log,
        **extra,
    }
    with atomic_outputs(force=True) as stage:  # the run's own checkpoint
        torch.save(state, stage(path))


def read_checkpoint(path: Path) -> dict:
    """The checkpoint's state, read as data and checked (module docstring).

    Raises
    ------
    InputError
        If there is no checkpoint, it cannot be read, a key is missing, ``field`` is not a
        table of tensors, or a tensor is not one a checkpoint may hold.
    """
    if not path.is_file():
        raise InputError(f"{path.parent} holds no checkpoint ({CHECKPOINT}): train it first")
    size = path.stat().st_size
    _check_archive(path, size)
    try:
        with warnings.catch_warnings():  # torch warns on what it refuses: the error says it
            warnings.simplefilter("ignore")
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a damaged or unsafe file
        raise InputError(f"cannot read checkpoint {path}: {first_line(exc)}") from None
    missing = [key for key in KEYS if not isinstance(state, dict) or key not in state]
    if missing:
        raise InputError(f"checkpoint {path} lacks {', '.join(missing)}")
    field = state["field"]
    if not isinstance(field, dict) or not all(
            isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in field.items()):
        raise InputError(f"checkpoint {path}: field must map names to tensors")
    declared = sum(_checked(tensor, path) for tensor in _tensors(state, path))
    if declared > DECLARED_PER_BYTE * size + DECLARED_SLACK:
        raise InputError(f"checkpoint {path}: its tensors declare {declared} bytes, more than "
                         f"{DECLARED_PER_BYTE} times the file's {size}")
    return state


def _check_archive(path: Path, size: int) -> None:
    """InputError unless ``path`` is a zip archive (torch's format) whose members hold at most
    the file's bytes: torch allocates each member's declared size before reading it."""
    try:
        with zipfile.ZipFile(path) as archive:
            declared = sum(info.file_size for info in archive.infolist())
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        raise InputError(f"cannot read checkpoint {path}: not a zip archive as torch.save "
                         f"writes ({first_line(exc)})") from None
    if declared > size:
        raise InputError(f"checkpoint {path}: its archive declares {declared} bytes in a file "
                         f"of {size}")


def _tensors(value, path: Path, depth: int = 0):
    """Every tensor in ``value``'s nested dicts, lists and tuples."""
    if depth > MAX_DEPTH:
        raise InputError(f"checkpoint {path} nests values more than {MAX_DEPTH} deep")
    if isinstance(value, torch.Tensor):
        yield value
    elif isinstance(value, dict):
        for item in value.values():
            yield from _tensors(item, path, depth + 1)
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from _tensors(item, path, depth + 1)


def _checked(tensor: torch.Tensor, path: Path) -> int:
    """The bytes ``tensor`` declares; InputError unless it is a dense tensor of ``DTYPES``
    whose storage holds them."""
    if tensor.layout != torch.strided or tensor.is_quantized or tensor.dtype not in DTYPES:
        raise InputError(f"checkpoint {path} holds a tensor of {tensor.dtype} "
                         f"({tensor.layout}); a checkpoint holds dense numbers only")
    declared = tensor.numel() * tensor.element_size()
    held = tensor.untyped_storage().nbytes() - tensor.storage_offset() * tensor.element_size()
    if declared > held:
        raise InputError(f"checkpoint {path} holds a tensor of shape {tuple(tensor.shape)} "
                         f"whose storage has {max(held, 0)} of its {declared} bytes")
    return declared


def load_optimisers(optimisers: list, states: list, rundir: Path) -> None:
    """Resume ``optimisers`` from a checkpoint's ``states``; InputError when they do not fit
    the run's parameters (a damaged or foreign checkpoint)."""
    try:
        for optimiser, state in zip(optimisers, states, strict=True):
            optimiser.load_state_dict(state)
            for group in optimiser.param_groups:
                for p in group["params"]:
                    moments = optimiser.state.get(p, {}).get("exp_avg", p)
                    if moments.shape != p.shape:
                        raise ValueError("moments of another shape")
    except (ValueError, KeyError, TypeError):
        raise InputError(f"{rundir} was trained with other optimisers than its parameters "
                         "take", fixes=[("force", "to start afresh")]) from None
