"""Names say what a thing is (issue 64): no two top-level classes of the library and the stage scripts share a
name, so a class named in a message, a docstring or a traceback is one class."""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = ("pipeline", "stages")


def class_homes(sources: dict[str, str]) -> dict[str, list[str]]:
    """Top-level class name -> the files (of ``sources``: path -> text) that define it."""
    homes = defaultdict(list)
    for path, text in sorted(sources.items()):
        for node in ast.parse(text).body:
            if isinstance(node, ast.ClassDef):
                homes[node.name].append(path)
    return homes


def shared_names(sources: dict[str, str]) -> list[str]:
    """One line per class name that more than one file of ``sources`` defines."""
    return [f"{name}: {', '.join(paths)}" for name, paths in class_homes(sources).items() if len(paths) > 1]


def test_no_two_classes_share_a_name():
    sources = {p.relative_to(ROOT).as_posix(): p.read_text() for d in FOLDERS for p in (ROOT / d).rglob("*.py")}
    assert len(sources) > 100
    assert not shared_names(sources)


def test_the_check_finds_two_classes_of_one_name():
    sources = {"a.py": "class Inputs:\n    pass\n", "b.py": "class Inputs:\n    pass\nclass Other:\n    pass\n"}
    assert shared_names(sources) == ["Inputs: a.py, b.py"]
