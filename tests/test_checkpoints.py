"""Checkpoints from elsewhere are checked like stacks: every tensor's type, dtype, shape and
count before anything is computed from it, in one line and exit code 2."""

import shutil
import struct

import pytest

from .hostile import capped, check_refused

torch = pytest.importorskip("torch")

from nerf_stage.cli import main as nerf_stage  # noqa: E402
from nerf_stage.train.checkpoint import CHECKPOINT  # noqa: E402


def export_command(rundir, out) -> int:
    return nerf_stage(["export", str(rundir), "-o", str(out)])


def _resaved(run, folder, change):
    """A copy of ``run`` in ``folder`` whose checkpoint's state went through ``change``."""
    shutil.copytree(run, folder)
    state = torch.load(folder / CHECKPOINT, weights_only=True)
    change(state)
    torch.save(state, folder / CHECKPOINT)
    return folder


def _repeated(state):
    """Every splat tensor a view repeating its first row 10^9 times: a few kilobytes."""
    state["field"] = {k: v[:1].expand(10**9, *v.shape[1:]) for k, v in state["field"].items()}


def _half(state):
    state["field"] = {k: v.half() for k, v in state["field"].items()}


def _listed(state):
    state["field"]["means"] = state["field"]["means"].tolist()


def _integers(state):
    state["field"]["opacities"] = state["field"]["opacities"].long()


def _complex(state):
    state["field"]["means"] = state["field"]["means"].to(torch.complex64)


def _many_views(state):
    """A thousand names for one storage: declared far beyond what the file holds."""
    big = torch.zeros(1 << 18)
    state["extra"] = [big] * 1000


CASES = {"repeated rows": (_repeated, "storage has"), "as a list": (_listed, "names to tensors"),
         "integers": (_integers, "floating-point"), "complex": (_complex, "complex64"),
         "many views": (_many_views, "times the file")}


@pytest.mark.parametrize("case", list(CASES))
def test_a_crafted_splat_checkpoint_is_refused_before_allocation(splat_scene_run, tmp_path,
                                                                 case):
    change, message = CASES[case]
    run = _resaved(splat_scene_run, tmp_path / "run", change)
    code, err = capped(export_command, run, tmp_path / "out.ply")
    check_refused(code, err)
    assert message in err and not (tmp_path / "out.ply").exists()


def test_splats_in_half_precision_are_read(splat_scene_run, tmp_path):
    run = _resaved(splat_scene_run, tmp_path / "run", _half)
    assert export_command(run, tmp_path / "out.ply") == 0


def test_an_archive_that_declares_more_than_it_holds_is_refused(splat_scene_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(splat_scene_run, run)
    data = bytearray((run / CHECKPOINT).read_bytes())
    entry = data.index(b"PK\x01\x02")  # the first member's central directory entry
    data[entry + 24:entry + 28] = struct.pack("<I", 0xFFFFFFF0)  # its uncompressed size
    (run / CHECKPOINT).write_bytes(bytes(data))
    code, err = capped(export_command, run, tmp_path / "out.ply")
    check_refused(code, err)
    assert "archive" in err or "checkpoint" in err


def test_a_field_checkpoint_whose_field_is_not_tensors_is_refused(scene_run, tmp_path):
    run = _resaved(scene_run, tmp_path / "run", lambda s: s["field"].update(extra=[1.0] * 3))
    code, err = capped(export_command, run, tmp_path / "out.ply")
    check_refused(code, err)
    assert "names to tensors" in err
