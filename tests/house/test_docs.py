"""The README guides (short, no issue log, links that resolve); reference text lives in docs/."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
MAX_README_LINES = 110


def _links(text: str) -> list[str]:
    return [m for m in re.findall(r"\]\(([^)#\s]+)", text) if not m.startswith(("http://", "https://"))]


def test_readme_is_short_and_has_the_two_commands():
    text = README.read_text()
    assert len(text.splitlines()) <= MAX_README_LINES
    assert "make demo" in text and "make test" in text


def test_readme_and_docs_carry_no_issue_numbers():
    for path in [README, *sorted((ROOT / "docs").glob("*.md"))]:
        hits = re.findall(r"\bissues? \d+", path.read_text(), flags=re.IGNORECASE)
        assert not hits, f"{path.name}: {hits}"


def test_every_relative_link_resolves():
    for path in [README, *sorted((ROOT / "docs").glob("*.md"))]:
        for link in _links(path.read_text()):
            target = (path.parent / link).resolve()
            if "shared/" in link and not target.exists():
                continue  # measurements sit beside the checkout, not in it
            assert target.exists(), f"{path.name}: broken link {link}"


def test_the_paper_is_cited_by_its_title_not_by_a_path_outside_the_repository():
    """A user's clone has no ``../shared/paper/``: the README, docs and code name the paper by its title and
    its equations by label (``eq:sdf-target``)."""
    texts = [README, *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "pipeline").rglob("*.py")),
             *sorted((ROOT / "stages").glob("*.py"))]
    cited = [p.relative_to(ROOT).as_posix() for p in texts if "shared/paper" in p.read_text()]
    assert not cited, f"a path to the paper outside the repository in {cited}"


def test_the_methods_table_in_the_docs_names_exactly_the_method_table():
    from pipeline.methods import METHODS

    text = (ROOT / "docs" / "pipeline.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| `")]
    named = [n for row in rows for n in re.findall(r"`(\w+)`", row.split("|")[1])]
    assert sorted(named) == sorted(METHODS), "docs/pipeline.md's methods table and pipeline.methods.METHODS differ"


def test_readme_explains_its_terms():
    text = README.read_text()
    glossary = text.split("## Terms", 1)[1].split("\n## ", 1)[0]
    for term in ("vote", "gate", "ceiling", "noise floor", "primary endpoint", "lockbox"):
        assert f"| {term} |" in glossary, term
