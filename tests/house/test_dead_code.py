"""No dead code (issues 45, 64): every public top-level function and class of the library and the stage scripts,
and every public method of their classes, is used by the code that ships -- the library (the CLI included), the
stage scripts, benchmarks/ and tools/.  A use in a test or a doc does not count.

Uses are read with ast, not as words: a name, an imported name, an attribute (``obj.answer(...)`` uses a method
named ``answer``) or a string that is a dotted or ``module:Name`` reference (the lazy tables).  A method counts
only as an attribute or a reference; a variable of the same name is not a use of it.  Docstrings and ``__all__``
lists are not uses.  A decorated definition (a click command, a validator) is reached through its decorator and
is not checked; a property, static or class method is.  What stays without a use is in :data:`KEPT`, with why.
"""

from __future__ import annotations

import ast
import re
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DEFINED_IN = ("pipeline", "stages")
USED_IN = ("pipeline", "stages", "benchmarks", "tools")
#: decorators that leave a method called by its name
ACCESSORS = {"property", "cached_property", "staticmethod", "classmethod"}
#: a string naming code: ``pipeline.teachers.sam3:Sam3Teacher``, ``answer``
REFERENCE = re.compile(r"[A-Za-z_][\w.]*(:[\w.]+)?")
#: kept without a use in the shipped code, and why (path:name)
KEPT = {
    # DESIGN.md's public API: notebooks and external checks call these
    "pipeline/geometry.py:sdf_target": "DESIGN.md public API",
    "pipeline/geometry.py:skeleton_target": "DESIGN.md public API",
    "pipeline/metrics.py:precision_recall": "DESIGN.md public API",
    # one image's metric, beside DESIGN.md's image_iou and boundary_f1 (the batched path is tested against them)
    "pipeline/metrics.py:mask_boundary": "the per-image definition score_masks is tested against",
    "pipeline/metrics.py:small_region_iou": "the per-image definition score_masks is tested against",
    "pipeline/stats.py:paired_hierarchical_bootstrap": "the S = 1 definition paired_seed_bootstrap is tested against",
    # the plug-in API (docs/pipeline.md, "How to extend"): a user's code calls it
    "pipeline/teacher_table.py:unregister_teacher": "plug-in API",
    "pipeline/labeling/formats.py:unregister_format": "plug-in API",
    # click calls a group's hooks
    "pipeline/cli/main.py:LazyGroup.list_commands": "click.Group hook",
    "pipeline/cli/main.py:LazyGroup.get_command": "click.Group hook",
    # the suite's fitted tiny SAM 3 (tests/conftest.py); docs/performance.md's bf16 gate is measured on it
    "pipeline/teachers/tiny_sam3.py:fit_tiny_sam3": "the fitted tiny teacher of the suite and of the bf16 gate",
}


def _checked(node: ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef, method: bool) -> bool:
    names = {getattr(d.func if isinstance(d, ast.Call) else d, "attr", None)
             or getattr(d.func if isinstance(d, ast.Call) else d, "id", None) for d in node.decorator_list}
    return not node.name.startswith("_") and (names <= ACCESSORS if method else not names)


def definitions(sources: dict[str, str]) -> list[tuple[str, str]]:
    """(path, name) of each public top-level function and class of ``sources`` (path -> text), and
    (path, ``Class.method``) of each public method of a top-level class."""
    out = []
    for path, text in sorted(sources.items()):
        for node in ast.parse(text).body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and _checked(node, False):
                out.append((path, node.name))
            if isinstance(node, ast.ClassDef):
                out += [(path, f"{node.name}.{m.name}") for m in node.body
                        if isinstance(m, (ast.FunctionDef, ast.AsyncFunctionDef)) and _checked(m, True)]
    return out


def uses(text: str) -> tuple[Counter, Counter]:
    """(every use of a name, the uses a method can have: attributes and references) in one module's source."""
    tree = ast.parse(text)
    not_uses = set()
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body
                and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)):
            not_uses.add(id(body[0].value))  # a docstring
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets):
            not_uses.update(id(n) for n in ast.walk(node.value))  # exported is not used
    names, attributes = Counter(), Counter()
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            names[node.id] += 1
        elif isinstance(node, ast.alias):
            names[node.name.rsplit(".", 1)[-1]] += 1
        elif isinstance(node, ast.Attribute):
            attributes[node.attr] += 1
        elif (isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in not_uses
              and REFERENCE.fullmatch(node.value)):
            attributes.update(re.split(r"[.:]", node.value))
    return names + attributes, attributes


def unused(defs: list[tuple[str, str]], texts) -> list[str]:
    """``path:name`` of each definition of ``defs`` with no use in ``texts``."""
    every, attributes = Counter(), Counter()
    for text in texts:
        n, a = uses(text)
        every, attributes = every + n, attributes + a
    return [f"{path}:{name}" for path, name in defs
            if not (attributes[name.rsplit(".", 1)[1]] if "." in name else every[name])]


def test_every_public_function_class_and_method_is_used():
    defined = {p.relative_to(REPO).as_posix(): p.read_text() for d in DEFINED_IN for p in (REPO / d).rglob("*.py")}
    shipped = [p.read_text() for d in USED_IN for p in (REPO / d).rglob("*.py")]
    dead = unused(definitions(defined), shipped)
    assert not [d for d in dead if d not in KEPT], "no use outside tests and docs"
    assert not [k for k in KEPT if k not in dead], "used now: leave KEPT"


def test_the_check_sees_methods_attributes_and_not_tests_or_docs():
    lib = ('"""Docs name forgotten_helper and Teacher.answer."""\n__all__ = ["forgotten_helper"]\n\n'
           "class Teacher:\n    def answer(self):\n        pass\n\n    def ask(self):\n        pass\n\n"
           "    @property\n    def size(self):\n        return 1\n\n"
           "def used():\n    pass\n\ndef forgotten_helper():\n    pass\n")
    caller = "from lib import used\n\nanswer = 1\nused()\nTeacher().ask()\nprint(Teacher().size, answer)\n"
    test = "from lib import forgotten_helper\nforgotten_helper()\nTeacher().answer()\n"
    defs = definitions({"lib.py": lib})
    assert defs == [("lib.py", "Teacher"), ("lib.py", "Teacher.answer"), ("lib.py", "Teacher.ask"),
                    ("lib.py", "Teacher.size"), ("lib.py", "used"), ("lib.py", "forgotten_helper")]
    # the test file is not searched: a use there does not count; a variable named answer is not the method
    assert unused(defs, [lib, caller]) == ["lib.py:Teacher.answer", "lib.py:forgotten_helper"]
    assert unused(defs, [lib, caller, test]) == []
    assert unused(defs, [lib, caller.replace("Teacher().ask()", "getattr(Teacher(), 'ask')()")]) == \
        ["lib.py:Teacher.answer", "lib.py:forgotten_helper"]
