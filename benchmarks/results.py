"""Benchmark results as data: each benchmark writes ``benchmarks/results/NAME.json`` (its
scores, the command that made them, the commit, the machine, the library versions and the
date), and ``report.py`` renders the tables of ``docs/results.md`` from those files alone
(gsplat's ``stats/*.json``; nerfacc's "updated on DATE with nerfacc==X").

A result's ``tables`` are what the page shows, each ``{"title", "columns", "rows"}`` as
``table`` makes them (and prints, as markdown, while the benchmark runs).
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


def table(title: str, columns: list[str], rows: list[list]) -> dict:
    """A table of a result, printed now as markdown; numpy scalars become plain numbers."""
    made = {"title": title, "columns": list(columns),
            "rows": [[_plain(value) for value in row] for row in rows]}
    print("\n" + markdown(made, "###"))
    return made


def markdown(made: dict, heading: str) -> str:
    """A ``table`` as markdown under its title."""
    lines = [f"{heading} {made['title']}", "", "| " + " | ".join(made["columns"]) + " |",
             "|" + "---|" * len(made["columns"])]
    lines += ["| " + " | ".join(_cell(value) for value in row) + " |" for row in made["rows"]]
    return "\n".join(lines) + "\n"


def _plain(value):
    return value.item() if hasattr(value, "item") else value


def _cell(value) -> str:
    if isinstance(value, float):
        return f"{value:.3g}" if abs(value) < 1e4 else f"{value:.3e}"
    return str(value)


def write_result(name: str, title: str, tables: list[dict], results: dict) -> Path:
    """Write ``results/NAME.json``: the ``tables`` the page shows under ``title``, the
    ``results`` behind them (any JSON), and how they were made (``sys.argv``, ``commit``,
    ``machine``, ``versions``, the date); written whole, then renamed into place."""
    RESULTS.mkdir(exist_ok=True)
    record = {"name": name, "title": title, "command": " ".join(["python", *sys.argv]),
              "commit": commit(), "date": datetime.date.today().isoformat(),
              "machine": machine(), "versions": versions(), "tables": tables,
              "results": results}
    path = RESULTS / f"{name}.json"
    staged = path.with_suffix(".json.part")
    staged.write_text(json.dumps(record, indent=1, default=_plain) + "\n")
    staged.replace(path)
    print(f"wrote {path}")
    return path
