"""The test folder's own rule (tests/conftest.py): no module under tests/ imports a test module
(``test_*.py``); shared fixtures live in conftest.py and shared builders in ``tests/builders/``,
imported as ``tests.builders.name`` (a bare ``_name`` would load a second copy through pytest's path entry)."""

from __future__ import annotations

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]


def _imported(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, dotted module name) of every import in ``tree``: import / from-import statements (``from
    tests import test_x`` counts as ``tests.test_x``) and ``__import__`` / ``import_module`` calls with a
    constant name."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, node.module))
            out += [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
        elif isinstance(node, ast.ImportFrom):  # relative: "from . import test_x", "from .test_x import y"
            out += [(node.lineno, f"{node.module or ''}.{a.name}".lstrip(".")) for a in node.names]
            if node.module:
                out.append((node.lineno, node.module))
        elif (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
              and isinstance(node.args[0].value, str)
              and getattr(node.func, "id", getattr(node.func, "attr", None)) in ("__import__", "import_module")):
            out.append((node.lineno, node.args[0].value))
    return out


def layout_violations(source: str, local: set[str]) -> list[str]:
    """What ``source`` (a module under tests/) imports against the folder's rule, ``local`` being the
    module names of tests/ (file stems)."""
    bad = []
    for line, name in _imported(ast.parse(source)):
        parts = name.split(".")
        if parts[-1].startswith("test_") and parts[-1] in local and (len(parts) == 1 or parts[0] == "tests"):
            bad.append(f"line {line}: imports the test module {name}")
        elif len(parts) == 1 and parts[0] in local and parts[0] != "conftest":
            bad.append(f"line {line}: imports the helper {name} without the tests. prefix")
        elif parts[-1] == "conftest" and parts[:-1] in ([], ["tests"]):
            bad.append(f"line {line}: imports conftest (its fixtures reach every test by name)")
    return bad


def test_the_checker_flags_every_form_of_importing_a_test_module():
    local = {"test_training", "test_deploy", "_tiny_train", "conftest"}
    for src in ("from tests.test_training import tiny_cfg", "import test_deploy", "from test_deploy import RES",
                "from tests import test_training", "import tests.test_training as t",
                "def f():\n    from test_training import tiny\n", "__import__('tests.test_deploy')",
                "importlib.import_module('test_training')", "from _tiny_train import tiny_cfg",
                "from conftest import tiny"):
        assert layout_violations(src, local), src
    for src in ("from tests.builders.training import tiny_cfg", "import pytest", "from pipeline.stats import test_x",
                "from tests.builders.training import test_helper_name"):
        assert not layout_violations(src, local), src


def test_no_module_under_tests_imports_a_test_module():
    files = sorted(TESTS.rglob("*.py"))
    local = {p.stem for p in files}
    assert {"conftest", "test_training", "training"} <= local
    bad = {str(p.relative_to(TESTS)): v for p in files if (v := layout_violations(p.read_text(), local))}
    assert not bad, f"test modules share fixtures through tests/conftest.py and builders through tests/builders/: {bad}"
