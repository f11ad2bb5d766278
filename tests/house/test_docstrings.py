"""The exported surface's docstrings are contracts: every parameter, return and error raised is named.

The surface is what each module's ``__all__`` lists (issue 64), not a list of files.  Ruff holds the whole of
``pipeline/`` to pydocstyle's numpy convention (pyproject.toml); where a module has ``__all__``, ruff's missing-
docstring rules (D1xx) treat the names it leaves out as private, and its form rules check every docstring
present.  This test checks what no stable ruff rule does, by parsing the source (ast):

* every module under ``pipeline/`` that defines a public name has an ``__all__``, and every name another package
  of the project (``pipeline.*`` subpackage, ``stages``, ``benchmarks``, ``tools``) imports from it is in that
  ``__all__``: the surface cannot be narrowed to dodge the contract;
* every exported function or class has a docstring; every parameter of an exported function or public method
  (``self``/``cls`` aside) is named in its Parameters section (a class's ``__init__`` parameters in the class
  docstring or ``__init__``'s own); one that returns a value has a Returns section (Yields for a generator);
* every exception class it raises in its own body (``raise X(...)``, ``raise X``) is named in its Raises section;
* every field of an exported dataclass or NamedTuple is named in its Attributes (or Parameters) section.

A click command is exempt (ruff's ``ignore-decorators`` too): its contract is its ``--help``, written with
``help=`` on each option, and a numpydoc section in its docstring would show there.
"""

from __future__ import annotations

import ast
import inspect
import tomllib
from pathlib import Path

from pipeline.runtime.codeversion import module_name

ROOT = Path(__file__).resolve().parents[2]
#: methods checked besides the public ones: what a caller calls by another spelling
CALLED_DUNDERS = ("__init__", "__call__")
#: the packages outside ``pipeline`` whose imports of the library count as crossing a package boundary
IMPORTERS = ("pipeline", "stages", "benchmarks", "tools")
#: decorators whose function is a property: its docstring describes the value, with no Returns section
PROPERTIES = ("property", "cached_property")

# PENDING (issue 64): library files kept out of the contract while another branch edits them: ruff ignores D on
# them (a per-file-ignores entry in pyproject.toml, checked equal to this list below) and this test skips them.
# A folder ends with "/".  Empty: every library module has its ``__all__`` and contracts.
PENDING: tuple[str, ...] = ()

# UNFINISHED (issue 64): library modules that have their ``__all__`` (checked below) but whose exported names
# have no full contract yet; ruff ignores D on them (a per-file-ignores entry) and the contract check skips them.
# Empty: every exported name has its contract.
UNFINISHED: tuple[str, ...] = ()


def pending(rel: str) -> bool:
    """Whether the repository path ``rel`` is on the :data:`PENDING` list."""
    return any(rel == p or (p.endswith("/") and rel.startswith(p)) for p in PENDING)


def _ruff_lint() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["ruff"]["lint"]


def click_decorators() -> tuple[str, ...]:
    """The decorators ruff's pydocstyle ignores (``ignore-decorators``): click's command and group."""
    return tuple(_ruff_lint()["pydocstyle"].get("ignore-decorators", ()))


def library_modules(unfinished: bool = True) -> dict[str, Path]:
    """Every module under ``pipeline/`` but the :data:`PENDING` ones (and the :data:`UNFINISHED` ones unless
    ``unfinished``), by dotted name."""
    return {module_name(p): p for p in sorted((ROOT / "pipeline").rglob("*.py"))
            if not pending(rel := p.relative_to(ROOT).as_posix()) and (unfinished or rel not in UNFINISHED)}


def exported(tree: ast.Module) -> list[str] | None:
    """The module's ``__all__`` (a literal list or tuple), or None when it has none."""
    for node in tree.body:
        if isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
                return list(ast.literal_eval(node.value))
    return None


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


def result_section(fn: ast.AST) -> str | None:
    """The section ``fn``'s result needs: "Yields" for a generator, "Returns" when its own body returns a value."""
    nodes = list(_own_nodes(fn))
    if any(isinstance(n, (ast.Yield, ast.YieldFrom)) for n in nodes):
        return "Yields"
    returns = any(isinstance(n, ast.Return) and n.value is not None
                  and not (isinstance(n.value, ast.Constant) and n.value.value is None) for n in nodes)
    return "Returns" if returns else None


def parameters(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> list[str]:
    """The parameter names of ``fn``, ``self`` and ``cls`` aside."""
    a = fn.args
    names = [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
    names += [x.arg for x in (a.vararg, a.kwarg) if x is not None]
    return [n for n in names if n not in ("self", "cls")]


def _decorator_names(node: ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef) -> set[str]:
    return {ast.unparse(d.func if isinstance(d, ast.Call) else d) for d in node.decorator_list}


def _is_record(cls: ast.ClassDef) -> bool:
    """A dataclass or a NamedTuple: its annotated fields are its constructor's parameters."""
    named = {n.split(".")[-1] for n in _decorator_names(cls)}
    bases = {b.id if isinstance(b, ast.Name) else getattr(b, "attr", None) for b in cls.bases}
    return "dataclass" in named or "NamedTuple" in bases


def check_source(source: str, where: str, names: list[str] | None = None,
                 exempt: tuple[str, ...] = ("click.command", "click.group")) -> tuple[list[str], dict[str, int]]:
    """(problems, counts) of one module's exported names (``names``; default: its ``__all__``).

    ``counts`` holds the functions, parameters, raised classes and record fields checked; ``exempt`` names the
    decorators (click's) whose functions are skipped.
    """
    problems: list[str] = []
    counts = {"functions": 0, "parameters": 0, "raises": 0, "fields": 0}
    tree = ast.parse(source)
    names = exported(tree) if names is None else names

    def check_function(fn, qualname: str, class_doc: str | None = None) -> None:
        doc = ast.get_docstring(fn)
        counts["functions"] += 1
        if doc is None and fn.name != "__init__":
            problems.append(f"{where}: {qualname}: no docstring")
        listed = documented_names(doc, "Parameters", "Other Parameters")
        if fn.name == "__init__":
            listed |= documented_names(class_doc, "Parameters", "Other Parameters")
        for p in parameters(fn):
            counts["parameters"] += 1
            if p not in listed:
                problems.append(f"{where}: {qualname}: parameter {p!r} not in its Parameters section")
        result = result_section(fn)
        if result and fn.name != "__init__" and not _decorator_names(fn) & set(PROPERTIES) \
                and result not in sections(doc):
            problems.append(f"{where}: {qualname}: returns a value but has no {result} section")
        raises = documented_raises(doc)
        for exc in sorted(raised_classes(fn)):
            counts["raises"] += 1
            if exc not in raises:
                problems.append(f"{where}: {qualname}: raises {exc} but its Raises section does not name it")

    def public(name: str) -> bool:
        return not name.startswith("_") or name in CALLED_DUNDERS

    for node in tree.body:
        if getattr(node, "name", None) not in (names or ()) or \
                _decorator_names(node) & (set(exempt) | {e.rsplit(".", 1)[-1] for e in exempt if e.startswith("pipeline.")}):
            continue
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            check_function(node, node.name)
        elif isinstance(node, ast.ClassDef):
            class_doc = ast.get_docstring(node)
            if class_doc is None:
                problems.append(f"{where}: {node.name}: no docstring")
            if _is_record(node):
                fields = documented_names(class_doc, "Attributes", "Parameters")
                for item in node.body:
                    if isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name) \
                            and "ClassVar" not in ast.unparse(item.annotation):
                        counts["fields"] += 1
                        if item.target.id not in fields:
                            problems.append(f"{where}: {node.name}: field {item.target.id!r} not in its "
                                            "Attributes section")
            for item in node.body:
                if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)) and public(item.name):
                    check_function(item, f"{node.name}.{item.name}", class_doc)
    return problems, counts


def cross_package_uses() -> dict[str, set[tuple[str, str]]]:
    """module -> {(name, importer)} for every name a project module imports from a library module of another
    package: ``from M import name`` and ``import M as m`` ... ``m.name``, at any depth of the importer."""
    modules = {module_name(p) for p in (ROOT / "pipeline").rglob("*.py")}
    uses: dict[str, set[tuple[str, str]]] = {}
    for root in IMPORTERS:
        for path in sorted((ROOT / root).rglob("*.py")):
            importer = module_name(path)
            package = importer if path.name == "__init__.py" else importer.rpartition(".")[0]
            tree = ast.parse(path.read_text())
            aliases: dict[str, str] = {}
            found: set[tuple[str, str]] = set()
            for node in ast.walk(tree):
                if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module in modules:
                    for a in node.names:
                        if f"{node.module}.{a.name}" in modules:
                            aliases[a.asname or a.name] = f"{node.module}.{a.name}"
                        else:
                            found.add((node.module, a.name))
                elif isinstance(node, ast.Import):
                    aliases.update({a.asname or a.name: a.name for a in node.names if a.name in modules})
            for node in ast.walk(tree):
                if isinstance(node, ast.Attribute) and ast.unparse(node.value) in aliases:
                    found.add((aliases[ast.unparse(node.value)], node.attr))
            for module, name in found:
                home = module.rpartition(".")[0] if (ROOT / (module.replace(".", "/") + ".py")).is_file() else module
                if home != package and module != importer:
                    uses.setdefault(module, set()).add((name, importer))
    return uses


def test_the_lists_are_the_ones_ruff_ignores():
    """pyproject.toml's per-file-ignores of D inside ``pipeline/`` name the files of :data:`PENDING` and
    :data:`UNFINISHED`, no more, no less."""
    entries = [k for k, v in _ruff_lint()["per-file-ignores"].items() if v == ["D"] and not k.startswith("!")]
    globbed = {p.rstrip("*").rstrip("/") for k in entries for p in k.strip("{}").split(",")}
    assert globbed == {p.rstrip("/") for p in (*PENDING, *UNFINISHED)}


def test_every_module_has_all_naming_what_other_packages_import():
    problems = []
    modules = library_modules()
    uses = cross_package_uses()
    for name, path in modules.items():
        tree = ast.parse(path.read_text())
        names = exported(tree)
        defines_public = any(not getattr(n, "name", "_").startswith("_") for n in tree.body
                             if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)))
        if names is None:
            if defines_public:
                problems.append(f"{path.relative_to(ROOT)}: no __all__")
            continue
        for used, importer in sorted(uses.get(name, ())):
            if used not in names and not (used.startswith("__") and used.endswith("__")) and not (ROOT / "pipeline" / name.removeprefix("pipeline.").replace(".", "/")
                                          / f"{used}.py").is_file():
                problems.append(f"{path.relative_to(ROOT)}: {used} is imported by {importer} but not in __all__")
        bound = _bound_names(tree)
        problems += [f"{path.relative_to(ROOT)}: __all__ names {n}, which it does not define"
                     for n in names if n not in bound and "__getattr__" not in bound]  # lazy: pipeline/__init__
    assert not problems, "\n".join(problems)


def _bound_names(tree: ast.Module) -> set[str]:
    out = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            out.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                out.update(t.id for t in ast.walk(target) if isinstance(t, ast.Name))
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            out.update((a.asname or a.name).split(".")[0] for a in node.names)
    return out


def surface_check() -> tuple[list[str], dict[str, int], int]:
    """(problems, counts, exported names) over every library module's ``__all__``."""
    problems, total, n_exported = [], {}, 0
    exempt = click_decorators()
    for path in library_modules(unfinished=False).values():
        source = path.read_text()
        n_exported += len(exported(ast.parse(source)) or ())
        found, counts = check_source(source, str(path.relative_to(ROOT)), exempt=exempt)
        problems += found
        total = {k: total.get(k, 0) + v for k, v in counts.items()}
    return problems, total, n_exported


def test_the_exported_surface_names_every_parameter_return_raise_and_field():
    problems, total, n_exported = surface_check()
    assert n_exported > 80 and total["parameters"] > 200, (n_exported, total)  # the surface is all of __all__
    assert not problems, f"{len(problems)} gaps ({total}):\n" + "\n".join(problems)


BAD = '''
__all__ = ["Result", "f", "Thing", "g", "cmd"]


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

    @property
    def area(self):
        """The area."""
        return 1


def g():
    return 1


@click.command()
def cmd(a):
    pass


def not_exported(a):
    raise KeyError
'''


def test_the_check_finds_each_kind_of_gap():
    problems, counts = check_source(BAD, "bad.py")
    assert sorted(problems) == sorted([
        "bad.py: Result: field 'b' not in its Attributes section",
        "bad.py: f: parameter 'y' not in its Parameters section",
        "bad.py: f: parameter 'flag' not in its Parameters section",
        "bad.py: f: raises InputError but its Raises section does not name it",
        "bad.py: Thing.__init__: parameter 'colour' not in its Parameters section",
        "bad.py: g: no docstring",
        "bad.py: g: returns a value but has no Returns section",
    ])
    assert counts == {"functions": 4, "parameters": 6, "raises": 2, "fields": 2}


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
