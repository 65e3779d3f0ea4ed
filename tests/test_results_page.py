"""docs/results.md is rendered from benchmarks/results/*.json and nothing else."""

import importlib.util
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
_spec = importlib.util.spec_from_file_location("report", ROOT / "benchmarks" / "report.py")
report = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(report)


def test_the_results_page_matches_the_result_files():
    assert (ROOT / "docs" / "results.md").read_text() == report.render(), \
        "docs/results.md is stale: run python benchmarks/report.py"


def test_every_result_names_its_command_commit_machine_and_versions():
    for path in (ROOT / "benchmarks" / "results").glob("*.json"):
        record = json.loads(path.read_text())
        assert record["command"].startswith("python ") and record["commit"], path
        assert {"cpu", "cores", "memory_gb"} <= record["machine"].keys(), path
        assert "python" in record["versions"] and record["date"], path
        assert record["tables"], path
        assert all(len(row) == len(made["columns"]) for made in record["tables"]
                   for row in made["rows"]), path


def test_a_changed_result_changes_the_page(tmp_path):
    for path in (ROOT / "benchmarks" / "results").glob("*.json"):
        (tmp_path / path.name).write_text(path.read_text())
    record = json.loads(next(tmp_path.glob("*.json")).read_text())
    record["tables"][0]["rows"][0][0] = "changed"
    next(tmp_path.glob("*.json")).write_text(json.dumps(record))
    assert report.render(tmp_path) != report.render()
