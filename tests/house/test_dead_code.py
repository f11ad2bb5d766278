"""No dead code (issue 45): every public top-level function and class of the library and the commands is
named somewhere besides its own definition -- in the code, the benchmarks, the tools, the tests or the
docs.  A click command (decorated) is reached through its group and counts as used."""

from __future__ import annotations

import ast
import re
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DEFINED_IN = ("pipeline", "stages")
SEARCHED = ("pipeline", "stages", "benchmarks", "tools", "tests")


def definitions() -> list[tuple[str, str]]:
    out = []
    for folder in DEFINED_IN:
        for path in sorted((REPO / folder).rglob("*.py")):
            for node in ast.parse(path.read_text()).body:
                if (isinstance(node, (ast.FunctionDef, ast.ClassDef)) and not node.name.startswith("_")
                        and not node.decorator_list):
                    out.append((path.relative_to(REPO).as_posix(), node.name))
    return out


def corpus() -> str:
    files = [p for d in SEARCHED for p in (REPO / d).rglob("*.py")]
    files += [*(REPO / "docs").glob("*.md"), REPO / "README.md", REPO / "Makefile", REPO / "pyproject.toml"]
    return "\n".join(p.read_text() for p in files if p.is_file())


def unused(defs, text) -> list[str]:
    words = Counter(re.findall(r"\w+", text))
    return [f"{path}:{name}" for path, name in defs if words[name] < 2]


def test_every_public_function_and_class_is_used():
    assert not unused(definitions(), corpus())


def test_the_check_finds_a_function_nobody_calls():
    text = "def used():\n    pass\n\nused()\n\ndef forgotten_helper():\n    pass\n"
    defs = [("x.py", n.name) for n in ast.parse(text).body if isinstance(n, ast.FunctionDef)]
    assert unused(defs, text) == ["x.py:forgotten_helper"]
