"""The docs hold together: every relative link resolves, the reference pages stay short, and
every doc the code cites exists."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", ROOT / "CHANGELOG.md",
         *(p for p in (ROOT / "docs").rglob("*.md") if "archive" not in p.parts)]
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
CITED = re.compile(r"docs/[\w/.-]+\.md")


def test_every_relative_link_resolves():
    broken = [f"{page.relative_to(ROOT)}: {target}" for page in PAGES
              for target in LINK.findall(page.read_text())
              if "://" not in target and not (page.parent / target).exists()]
    assert not broken


def test_no_reference_page_is_over_400_lines():
    assert not [page.name for page in PAGES if len(page.read_text().splitlines()) > 400]


def test_the_docs_the_code_cites_exist():
    sources = [p for package in ("palette_core", "harmonize", "nerf_stage", "studio",
                                 "benchmarks", "tests") for p in (ROOT / package).rglob("*.py")]
    missing = {f"{path.relative_to(ROOT)}: {cited}" for path in sources
               for cited in CITED.findall(path.read_text()) if not (ROOT / cited).exists()}
    assert not missing
