"""The public surface's docstrings are contracts: every parameter and every error raised is named.

The modules are the ones pyproject.toml's ruff config holds to pydocstyle's numpy convention (the negated
``per-file-ignores`` pattern: everything else ignores ``D``).  Ruff checks the form, and D417 the Parameters
section where one exists; this test checks what no stable ruff rule does, by parsing the source (ast):

* every parameter of a public function or method (``self``/``cls`` aside) is named in its docstring's
  Parameters section; a class's ``__init__`` parameters in the class docstring (or ``__init__``'s own);
* every exception class a public function raises in its own body (``raise X(...)``, ``raise X``) is named in
  its Raises section;
* every field of a public dataclass or NamedTuple is named in its Attributes (or Parameters) section.
"""

from __future__ import annotations

import ast
import glob
import inspect
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: methods checked besides the public ones: what a caller calls by another spelling
CALLED_DUNDERS = ("__init__", "__call__")


def surface_files() -> list[Path]:
    """The files ruff holds to the numpy docstring convention: the negated per-file-ignores pattern of ``D``."""
    lint = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["ruff"]["lint"]
    patterns = [k for k, v in lint["per-file-ignores"].items() if k.startswith("!") and "D" in v]
    assert len(patterns) == 1, f"expected one negated per-file-ignores pattern ignoring D, got {patterns}"
    inner = patterns[0][1:].strip("{}").split(",")
    files = sorted({Path(p) for pat in inner for p in glob.glob(str(ROOT / pat.strip()))})
    assert files, "the docstring-checked pattern matches no file"
    return files


def sections(doc: str | None) -> dict[str, list[str]]:
    """numpydoc sections of a docstring: header -> its entry names (the lines at the section's indentation)."""
    out: dict[str, list[str]] = {}
    lines = inspect.cleandoc(doc or "").splitlines()
    current = None
    for i, line in enumerate(lines):
        underline = lines[i + 1].strip() if i + 1 < len(lines) else ""
        if line.strip() and not line[0].isspace() and underline and set(underline) == {"-"}:
            current = out.setdefault(line.strip(), [])
        elif current is not None and line.strip() and not line[0].isspace() and set(line.strip()) != {"-"}:
            current.append(line)
    return out


def documented_names(doc: str | None, *headers: str) -> set[str]:
    """Names listed in the given sections: ``a, b : int`` -> {a, b}; ``*args`` -> args."""
    found: set[str] = set()
    secs = sections(doc)
    for header in headers:
        for entry in secs.get(header, []):
            found.update(n.strip().lstrip("*") for n in entry.split(" :")[0].split(","))
    return found


def documented_raises(doc: str | None) -> set[str]:
    """Exception class names of the Raises section (a dotted name counts by its last part)."""
    return {entry.split()[0].rstrip(":").split(".")[-1] for entry in sections(doc).get("Raises", [])}


def _own_nodes(fn: ast.AST):
    """The nodes of ``fn``'s body, not descending into nested functions, lambdas or classes."""
    stack = list(ast.iter_child_nodes(fn))
    while stack:
        node = stack.pop()
        yield node
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef)):
            stack.extend(ast.iter_child_nodes(node))


def raised_classes(fn: ast.AST) -> set[str]:
    """Exception classes ``fn`` raises in its own body (a re-raised variable is not a class)."""
    out = set()
    for node in _own_nodes(fn):
        if isinstance(node, ast.Raise) and node.exc is not None:
            exc = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
            name = exc.id if isinstance(exc, ast.Name) else exc.attr if isinstance(exc, ast.Attribute) else None
            if name and name[0].isupper():
                out.add(name)
    return out


def parameters(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> list[str]:
    a = fn.args
    names = [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
    names += [x.arg for x in (a.vararg, a.kwarg) if x is not None]
    return [n for n in names if n not in ("self", "cls")]


def _is_record(cls: ast.ClassDef) -> bool:
    """A dataclass or a NamedTuple: its annotated fields are its constructor's parameters."""
    decorators = [d.func if isinstance(d, ast.Call) else d for d in cls.decorator_list]
    named = {d.id if isinstance(d, ast.Name) else getattr(d, "attr", None) for d in decorators}
    bases = {b.id if isinstance(b, ast.Name) else getattr(b, "attr", None) for b in cls.bases}
    return "dataclass" in named or "NamedTuple" in bases


def check_source(source: str, where: str) -> tuple[list[str], dict[str, int]]:
    """(problems, counts) of one module's source: counts of functions, parameters and raised classes checked."""
    problems: list[str] = []
    counts = {"functions": 0, "parameters": 0, "raises": 0, "fields": 0}

    def check_function(fn, qualname: str, class_doc: str | None = None) -> None:
        doc = ast.get_docstring(fn)
        counts["functions"] += 1
        names = documented_names(doc, "Parameters", "Other Parameters")
        if fn.name == "__init__":
            names |= documented_names(class_doc, "Parameters", "Other Parameters")
        for p in parameters(fn):
            counts["parameters"] += 1
            if p not in names:
                problems.append(f"{where}: {qualname}: parameter {p!r} not in its Parameters section")
        listed = documented_raises(doc)
        for exc in sorted(raised_classes(fn)):
            counts["raises"] += 1
            if exc not in listed:
                problems.append(f"{where}: {qualname}: raises {exc} but its Raises section does not name it")

    def public(name: str) -> bool:
        return not name.startswith("_") or name in CALLED_DUNDERS

    for node in ast.parse(source).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
            check_function(node, node.name)
        elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            class_doc = ast.get_docstring(node)
            if _is_record(node):
                fields = documented_names(class_doc, "Attributes", "Parameters")
                for item in node.body:
                    if isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
                        counts["fields"] += 1
                        if item.target.id not in fields:
                            problems.append(f"{where}: {node.name}: field {item.target.id!r} not in its "
                                            "Attributes section")
            for item in node.body:
                if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)) and public(item.name):
                    check_function(item, f"{node.name}.{item.name}", class_doc)
    return problems, counts


def test_the_public_surface_names_every_parameter_raise_and_field():
    problems, total = [], {}
    for path in surface_files():
        found, counts = check_source(path.read_text(), str(path.relative_to(ROOT)))
        problems += found
        total = {k: total.get(k, 0) + v for k, v in counts.items()}
    assert total["functions"] > 100 and total["parameters"] > 200, total  # the pattern still matches the surface
    assert not problems, f"{len(problems)} gaps ({total}):\n" + "\n".join(problems)


BAD = '''
class Result(NamedTuple):
    """A result.

    Attributes
    ----------
    a : int
        The a.
    """

    a: int
    b: int


def f(x, y, *rest, flag=False):
    """Do f.

    Parameters
    ----------
    x, rest : int
        Named.

    Raises
    ------
    ValueError
        Never here.
    """
    def inner():
        raise KeyError("nested: not f's own raise")
    if flag:
        raise errors.InputError("x")
    raise ValueError("y")


class Thing:
    """A thing.

    Parameters
    ----------
    size : int
        Its size.
    """

    def __init__(self, size, colour):
        pass

    def _private(self, z):
        raise RuntimeError
'''


def test_the_check_finds_each_kind_of_gap():
    problems, counts = check_source(BAD, "bad.py")
    assert sorted(problems) == sorted([
        "bad.py: Result: field 'b' not in its Attributes section",
        "bad.py: f: parameter 'y' not in its Parameters section",
        "bad.py: f: parameter 'flag' not in its Parameters section",
        "bad.py: f: raises InputError but its Raises section does not name it",
        "bad.py: Thing.__init__: parameter 'colour' not in its Parameters section",
    ])
    assert counts == {"functions": 2, "parameters": 6, "raises": 2, "fields": 2}


def test_sections_read_numpydoc_entries():
    doc = """Summary.

    Parameters
    ----------
    a, b : int
        Two.
    *args : str
        More.

    Raises
    ------
    pipeline.runtime.errors.InputError
        When bad.
    """
    assert documented_names(doc, "Parameters") == {"a", "b", "args"}
    assert documented_raises(doc) == {"InputError"}
