"""Code versions derived from imports.

The project files a stage runs are both its code deps in dvc.yaml and its code version in every fingerprint,
so the two cannot disagree.  It imports nothing of the project: whatever it imported would be a code dep of
every stage.
"""

from __future__ import annotations

import ast
import functools
import hashlib
from pathlib import Path

__all__ = ["ROOT", "module_name", "code_deps", "code_version_of"]

ROOT = Path(__file__).resolve().parents[2]
PROJECT_PACKAGES = ("pipeline", "stages", "benchmarks", "tools")


def module_path(name: str, root: Path = ROOT) -> Path | None:
    """Find the file of a project module (``pipeline.geometry`` -> pipeline/geometry.py), or None."""
    parts = name.split(".")
    if parts[0] not in PROJECT_PACKAGES:
        return None
    base = root.joinpath(*parts)
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    f = base.with_suffix(".py")
    return f if f.is_file() else None


def module_name(path: Path, root: Path = ROOT) -> str:
    """Name the module of a project file (pipeline/geometry.py -> ``pipeline.geometry``; a package by its folder).

    Parameters
    ----------
    path : Path
        The file, under ``root``.
    root : Path
        The repository root.

    Returns
    -------
    str
        The dotted module name.
    """
    rel = path.relative_to(root).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path, root: Path = ROOT) -> set[str]:
    """Project modules imported anywhere in ``path`` (inside functions too), with their parent packages."""
    tree = ast.parse(path.read_text(), filename=str(path))
    me = module_name(path, root)
    is_pkg = path.name == "__init__.py"
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = me.split(".") if is_pkg else me.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            names.add(mod)
            names.update(f"{mod}.{a.name}" for a in node.names)  # ``from pkg import submodule``
    out: set[str] = set()
    for n in names:
        parts = n.split(".")
        for i in range(1, len(parts) + 1):
            out.add(".".join(parts[:i]))
    return {n for n in out if module_path(n, root) is not None}


@functools.lru_cache(maxsize=None)
def module_files(module: str, root: Path = ROOT) -> tuple[str, ...]:
    """Every project file that running ``module`` may execute, sorted, relative to ``root``."""
    start = module_path(module, root)
    if start is None:
        raise ValueError(f"{module}: not a project module")
    seen: set[Path] = set()
    parts = module.split(".")
    todo = [start] + [p for i in range(1, len(parts)) if (p := module_path(".".join(parts[:i]), root))]
    while todo:
        f = todo.pop()
        if f in seen:
            continue
        seen.add(f)
        todo.extend(module_path(m, root) for m in _imports(f, root))
    return tuple(sorted(p.relative_to(root).as_posix() for p in seen))


def code_deps(module: str, root: Path = ROOT, code_root: Path | None = None) -> list[str]:
    """List :func:`module_files` as dvc.yaml lists them: a sub-package whose every file is used by its folder.

    Parameters
    ----------
    module : str
        The stage's module (``stages.train``).
    root : Path
        The repository root.
    code_root : Path, optional
        A distill project's installed code: every file by its absolute path under it, since that project's
        .dvcignore cannot keep the installed code's bytecode out of a folder hash.

    Returns
    -------
    list of str
        The dependency paths, in :func:`module_files` order.
    """
    files = module_files(module, root)
    if code_root is not None:
        return [(Path(code_root) / rel).as_posix() for rel in files]
    out: list[str] = []
    done: set[str] = set()
    for rel in files:
        parent = str(Path(rel).parent)
        if parent in PROJECT_PACKAGES:  # top-level packages: file by file
            out.append(rel)
            continue
        if parent in done:
            continue
        members = {p.relative_to(root).as_posix() for p in (root / parent).rglob("*.py")}
        if members <= set(files):
            out.append(parent)
            done.add(parent)
        else:
            out.append(rel)
    return out


def code_version_of(module: str, root: Path = ROOT) -> str:
    """Hash the code a stage runs: its code version.

    sha256 (16 hex) over the names and bytes of :func:`module_files`.

    Parameters
    ----------
    module : str
        The stage's module.
    root : Path
        The repository root.

    Returns
    -------
    str
        16 hex digits.
    """
    h = hashlib.sha256()
    for rel in module_files(module, root):
        h.update(rel.encode())
        h.update((root / rel).read_bytes())
    return h.hexdigest()[:16]
