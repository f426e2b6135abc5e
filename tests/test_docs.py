"""The README is a front page and its figures are generated; the repository reads nothing outside itself."""

import re
from pathlib import Path

from tests.bench.figures import readme_blocks

ROOT = Path(__file__).resolve().parents[1]
TEXT = [p for pat in ("*.py", "*.md", "*.json", "*.toml", "*.yaml", "*.html", "Makefile", "run")
        for p in ROOT.rglob(pat)
        if not any(part in (".venv", ".git", "runs", ".bench", "build") or part.endswith(".egg-info")
                   for part in p.relative_to(ROOT).parts)]


def test_readme_is_a_front_page():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 300, len(lines)
    for needed in ("make demo", "make test", "ardflow diagnose", "ardflow serve", "--scheduler"):
        assert any(needed in line for line in lines), needed


def test_readme_figures_are_what_the_generated_file_renders():
    for held, rendered in readme_blocks():
        assert held == rendered, "README's generated block is stale: run python -m tests.bench.figures"


def test_links_in_readme_and_docs_resolve():
    for page in [ROOT / "README.md", *(ROOT / "docs").glob("*.md"), ROOT / "examples" / "data" / "README.md"]:
        for target in re.findall(r"\]\(([^)#\s]+)\)", page.read_text()):
            if "://" in target:
                continue
            assert (page.parent / target).exists(), f"{page.name}: broken link {target}"


def test_nothing_reads_outside_the_repository():
    offenders = [str(p.relative_to(ROOT)) for p in TEXT if p != Path(__file__)
                 and re.search(r"\.\./shared|parent\s*/\s*\"shared\"", p.read_text(errors="ignore"))]
    assert not offenders, offenders
