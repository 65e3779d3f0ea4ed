"""Writing outputs: checked up front, staged beside their place, published by rename.

Every command writes through here, so nothing is half-written and nothing the user
had is replaced without ``force``:

- files are staged as hidden temporaries in their final folder
  (``atomic_outputs``) and folders are built beside their final place
  (``publish_folder``); both are renamed into place only when everything has
  been written, and removed on any error, SIGINT, SIGTERM or SIGHUP
  (``cli.run_cli`` turns the signals into exceptions);
- without ``force`` the rename never replaces anything
  (``renameat2(RENAME_NOREPLACE)``), so an output that someone else created
  after the start-up check is kept and reported;
- temporaries are named ``.NAME.~PID~XXXXXXXX.tmp...``: after a SIGKILL nothing can
  clean up, so the next write into the same folder removes the temporaries of
  processes that no longer run (``sweep_stale``);
- files and folders get the permissions the umask allows, like any other file.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from PIL import Image

from .errors import InputError, OutputExists

_STALE = re.compile(r"^\..*\.~(\d+)~[^/]*$")


def _temp_name(name: str) -> str:
    """Prefix of a temporary for ``name``: hidden, and naming this process."""
    return f".{name}.~{os.getpid()}~"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def sweep_stale(folder: Path) -> None:
    """Remove the temporaries of processes that no longer run from ``folder``."""
    try:
        entries = list(folder.iterdir())
    except OSError:
        return
    for entry in entries:
        match = _STALE.match(entry.name)
        if not match or _alive(int(match.group(1))):
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextlib.contextmanager
def atomic_outputs(force: bool = False):
    """Stage output files and publish them together, or not at all.

    Yields a function ``stage(final_path) -> temp_path``: write to the temporary
    path it returns. When the block ends without error every staged file is
    renamed onto its final path; on error every temporary file is removed.
    Without ``force`` no existing file is replaced: if one appeared meanwhile,
    the files published so far are taken back and InputError names it.

    Raises
    ------
    InputError
        If two outputs have the same path, or (without ``force``) an output exists
        at publish time.
    """
    staged: dict[Path, Path] = {}
    created: list[Path] = []  # folders made for the outputs, removed again on error

    def stage(final: str | os.PathLike) -> Path:
        final = Path(final)
        if final in staged:
            raise InputError(f"two outputs would be written to {final}: give them distinct names")
        created.extend(reversed([p for p in final.parents if not p.exists()]))
        final.parent.mkdir(parents=True, exist_ok=True)
        sweep_stale(final.parent)
        fd, tmp = tempfile.mkstemp(prefix=_temp_name(final.stem), suffix=".tmp" + final.suffix,
                                   dir=final.parent)
        os.fchmod(fd, 0o666 & ~_umask())
        os.close(fd)
        staged[final] = Path(tmp)
        return Path(tmp)

    try:
        yield stage
        _publish_files(staged, force)
        created.clear()
    finally:
        for tmp in staged.values():
            tmp.unlink(missing_ok=True)
        for folder in reversed(created):
            with contextlib.suppress(OSError):
                folder.rmdir()  # only if empty


def _publish_files(staged: dict[Path, Path], force: bool) -> None:
    published = []
    try:
        for final, tmp in staged.items():
            if force:
                os.replace(tmp, final)
                continue
            try:
                rename_no_replace(tmp, final)
            except FileExistsError:
                raise OutputExists(f"output {final} appeared while writing; it was "
                                   "kept") from None
            published.append(final)
    except BaseException:
        for final in published:
            final.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def publish_folder(final: str | os.PathLike, force: bool = False) -> Iterator[Path]:
    """Build a folder beside ``final`` and rename it onto ``final`` when the block succeeds.

    Yields the staging folder. An existing ``final`` is replaced (moved aside,
    then deleted) only with ``force``; without it, an empty ``final`` is taken
    over and anything else that is there at publish time is kept and reported.
    On error the staging folder is removed.

    Raises
    ------
    InputError
        If ``final`` is not empty (without ``force``), now or at publish time.
    """
    final = Path(final)
    check_outdir(final, force)
    final.parent.mkdir(parents=True, exist_ok=True)
    sweep_stale(final.parent)
    staging = Path(tempfile.mkdtemp(prefix=_temp_name(final.name), dir=final.parent))
    try:
        os.chmod(staging, 0o777 & ~_umask())
        yield staging
        if force and final.exists():
            trash = Path(tempfile.mkdtemp(prefix=_temp_name(final.name + ".old"),
                                          dir=final.parent))
            os.replace(final, trash / "old")
            os.replace(staging, final)
            shutil.rmtree(trash)
            return
        with contextlib.suppress(FileNotFoundError, OSError):
            final.rmdir()  # only when empty: what check_outdir allowed
        try:
            rename_no_replace(staging, final)
        except FileExistsError:
            raise OutputExists(f"output folder {final} appeared while writing; it was "
                               "kept", "to replace it") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def rename_no_replace(source: Path, target: Path) -> None:
    """Rename ``source`` onto ``target`` unless ``target`` exists (FileExistsError), atomically
    with Linux's ``renameat2(RENAME_NOREPLACE)``, else by checking first."""
    renameat2 = getattr(_libc(), "renameat2", None)
    if renameat2 is None:
        if os.path.lexists(target):
            raise FileExistsError(errno.EEXIST, "exists", str(target))
        os.rename(source, target)
        return
    at_fdcwd, noreplace = -100, 1
    if renameat2(at_fdcwd, os.fsencode(source), at_fdcwd, os.fsencode(target), noreplace) != 0:
        code = ctypes.get_errno()
        if code in (errno.EEXIST, errno.ENOTEMPTY):
            raise FileExistsError(code, os.strerror(code), str(target))
        if code in (errno.ENOSYS, errno.EINVAL):  # file system without the flag
            if os.path.lexists(target):
                raise FileExistsError(errno.EEXIST, "exists", str(target))
            os.rename(source, target)
            return
        raise OSError(code, os.strerror(code), str(target))


def _libc():
    try:
        return ctypes.CDLL(None, use_errno=True)
    except OSError:
        return None


def check_writable(paths: list[Path], force: bool) -> None:
    """Fail early if an output file exists (without ``force``) or its folder cannot be written.

    Raises
    ------
    InputError
        Naming the first offending path.
    """
    for path in map(Path, paths):
        if path.exists() and not force:
            raise OutputExists(f"output {path} already exists")
        if path.is_dir():
            raise InputError(f"output {path} is a folder, expected a file path")
        check_parent(path)


def check_apart(outputs: list, inputs: list) -> None:
    """Fail early if an output is an input, lies inside an input folder (where the next run
    reads it as an input), or holds an input (replacing it would delete the input).

    Raises
    ------
    InputError
        Naming the output and the input.
    """
    for output in outputs:
        target = Path(os.path.abspath(output))
        for source in (Path(os.path.abspath(p)) for p in inputs):
            if (target == source or (source.is_dir() and target.is_relative_to(source))
                    or source.is_relative_to(target)):
                raise InputError(f"output {output} would land among the inputs ({source}): "
                                 "write it elsewhere")


def check_outdir(outdir: str | os.PathLike, force: bool) -> None:
    """Fail early if ``outdir`` is a file, a non-empty folder (without ``force``) or unwritable.

    Raises
    ------
    InputError
        Naming the folder and the reason.
    """
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise InputError(f"output {outdir} exists and is not a folder")
    if outdir.is_dir() and any(outdir.iterdir()) and not force:
        raise OutputExists(f"output folder {outdir} is not empty", "to replace it")
    check_parent(outdir)


def check_parent(path: Path) -> None:
    folder = next(p for p in [path.parent, *path.parent.parents] if p.exists())
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"cannot write output {path}: {folder} is not a writable folder")


def save_image(path: Path, rgb: np.ndarray) -> None:
    """Write (H, W, 3), (H, W, 4) or (H, W) floats in [0, 1] as an 8-bit image (suffix = format)."""
    data = np.round(np.clip(rgb, 0.0, 1.0) * 255).astype(np.uint8)
    fmt = Image.registered_extensions().get(Path(path).suffix.lower(), "PNG")
    Image.fromarray(data).save(path, format=fmt, **({"quality": 95} if fmt == "JPEG" else {}))
