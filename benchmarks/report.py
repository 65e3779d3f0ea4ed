"""Render ``docs/results.md`` from ``benchmarks/results/*.json`` (``results.py``): one
section a result, its table, and the line that says how, when and on what it was measured.

    python benchmarks/report.py            # write docs/results.md
    python benchmarks/report.py --check    # exit 1 if the page differs from the files
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from results import markdown

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
PAGE = ROOT / "docs" / "results.md"
HEADER = """# Results

Every number here is rendered from a file in `benchmarks/results/` that names the command,
the commit and the machine that produced it (`benchmarks/report.py`; a test holds this page
to those files). How each benchmark works is in its script's docstring.
"""


def render(results: Path = RESULTS) -> str:
    """The page for the result files in ``results``, in name order."""
    sections = [HEADER]
    for path in sorted(results.glob("*.json")):
        record = json.loads(path.read_text())
        machine = record["machine"]
        on = f"{machine['cpu']}, {machine['cores']} cores, {machine['memory_gb']} GB"
        if machine.get("gpu"):
            on += f", {machine['gpu']}"
        libraries = ", ".join(f"{k} {v}" for k, v in record["versions"].items())
        lines = [f"## {record['title']}", ""]
        lines += [markdown(made, "###") for made in record["tables"]]
        lines += [f"`{record['command']}` at `{record['commit']}` on {record['date']}; "
                  f"{on}; {libraries}. Data: `benchmarks/results/{path.name}`."]
        sections.append("\n".join(lines) + "\n")
    return "\n".join(sections)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--check", action="store_true",
                        help="exit 1 if docs/results.md differs from what the files give")
    args = parser.parse_args()
    page = render()
    if args.check:
        same = PAGE.is_file() and PAGE.read_text() == page
        print("docs/results.md matches benchmarks/results/" if same else
              "docs/results.md is stale: run python benchmarks/report.py")
        return 0 if same else 1
    PAGE.write_text(page)
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
