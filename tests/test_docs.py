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
    for doc, held, rendered in readme_blocks():
        assert held == rendered, f"{doc.name}'s generated block is stale: run python -m tests.bench.figures"


# a measured result typed by hand: "0.35 -> 0.30", "ln BF 3327", "free run 0.114", "(ln BF 206)"
MEASURED = re.compile(r"\d[\d.,]*(e-?\d+)?\s*(mV|rad|s|%)?\s*->\s*\**-?\d|ln BF [~=]?\s*\d|free-runs [\d.]+ ?(mV|rad)")


def test_no_figure_in_the_readme_or_docs_is_typed_by_hand():
    """Measured results live in generated blocks (from docs/figures.json) or in the tests that check them; what
    the docs may type is a setting, a default or a threshold."""
    offenders = []
    for page in [ROOT / "README.md", *(ROOT / "docs").glob("*.md")]:
        text = re.sub(r"<!-- (\w+):begin.*?<!-- \1:end -->", "", page.read_text(), flags=re.S)
        text = re.sub(r"```.*?```", "", text, flags=re.S)  # commands and their sample output
        for i, line in enumerate(text.splitlines(), 1):
            if MEASURED.search(line):
                offenders.append(f"{page.name}: {line.strip()[:100]}")
    assert not offenders, "\n".join(offenders)


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


def _modules() -> list[str]:
    """Every module of the three packages, by its path inside its folder (``loop/diagnose.py``, ``graph.py``)."""
    out = []
    for top in ("ardcore", "workers", "service"):
        for p in sorted((ROOT / top).rglob("*.py")):
            if p.name != "__init__.py":
                out.append(str(p.relative_to(ROOT / top)))
    return out


def test_every_module_is_named_in_the_architecture_page():
    text = (ROOT / "docs" / "architecture.md").read_text()
    missing = [m for m in _modules() if f"`{m}`" not in text]
    assert not missing, f"docs/architecture.md does not name {missing}"


def test_types_the_architecture_page_names_live_where_it_says():
    import ast

    for line in (ROOT / "docs" / "architecture.md").read_text().splitlines():
        cells = [c.strip() for c in line.split("|")]
        paths = [c.strip("`") for c in cells if re.fullmatch(r"`[a-z_]+/[a-z_]+\.py`", c)]
        if len(paths) != 1 or not (ROOT / "ardcore" / paths[0]).exists():
            continue
        tree = ast.parse((ROOT / "ardcore" / paths[0]).read_text())
        defined = {n.name for n in tree.body if isinstance(n, (ast.ClassDef, ast.FunctionDef))}
        defined |= {t.id for n in tree.body if isinstance(n, ast.Assign) for t in n.targets if isinstance(t, ast.Name)}
        named = re.findall(r"`([A-Z]\w+)`", cells[-2])
        assert set(named) <= defined, f"{paths[0]}: {set(named) - defined} not defined there"
