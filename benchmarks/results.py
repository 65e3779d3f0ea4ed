"""Benchmark results as data: each benchmark writes ``benchmarks/results/NAME.json`` (its
scores, the command that made them, the commit, the machine, the library versions and the
date), and ``report.py`` renders the tables of ``docs/results.md`` from those files alone
(gsplat's ``stats/*.json``; nerfacc's "updated on DATE with nerfacc==X").

A result's ``table`` is what the page shows: ``{"columns": [...], "rows": [[...], ...]}``.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
#: The libraries whose versions a result names.
LIBRARIES = ("numpy", "scipy", "numba", "torch", "pillow", "pycolmap", "gsply")


def machine() -> dict:
    """What the numbers were measured on: the processor, its cores, memory, and a GPU."""
    gpu = None
    try:
        import torch

        if torch.cuda.is_available():
            gpu = torch.cuda.get_device_name(0)
    except ImportError:
        pass
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return {"cpu": _cpu(), "cores": os.cpu_count(), "memory_gb": round(memory, 1),
            "gpu": gpu, "system": platform.platform(terse=True)}


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def versions() -> dict:
    """Python's version and those of ``LIBRARIES`` that are installed."""
    found = {"python": platform.python_version()}
    for name in LIBRARIES:
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return found


def commit() -> str:
    """The checkout's commit, with ``+changes`` when the tracked files differ from it."""
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, text=True,
                              capture_output=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=root, text=True, capture_output=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+changes" if dirty else "")


def write_result(name: str, results: dict, table: dict, title: str) -> Path:
    """Write ``results/NAME.json``: ``results`` (any JSON), the ``table`` the page shows under
    ``title``, and how they were made (``sys.argv``, ``commit``, ``machine``, ``versions``,
    the date); written whole, then renamed into place."""
    RESULTS.mkdir(exist_ok=True)
    record = {"name": name, "title": title, "command": " ".join(["python", *sys.argv]),
              "commit": commit(), "date": datetime.date.today().isoformat(),
              "machine": machine(), "versions": versions(), "table": table,
              "results": results}
    path = RESULTS / f"{name}.json"
    staged = path.with_suffix(".json.part")
    staged.write_text(json.dumps(record, indent=1) + "\n")
    staged.replace(path)
    return path
