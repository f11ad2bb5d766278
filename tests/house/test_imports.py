"""The import graph is the DAG: no circles among the project's modules, and imports sit at module top.

The rule (docs/decisions.md, "Imports"): every import is at the top of its module, except

* an optional or heavy third-party dependency listed in :data:`LAZY` -- imported where it is used, so
  that a module which only sometimes needs it does not pay for it (or fail without the extra);
* a project module that starts one of :data:`LAZY` (imports it at its top, directly or through its
  own top-level imports) which the importing module does not start itself: the same reason, one step
  removed (``geodistill --help`` must not start torch).

:data:`LAZY` is the one list of those dependencies, with the reason for each.

The layers (docs/decisions.md, "Layers"): :data:`LAYERS` is the one statement of the layer order, lowest
first; a module imports its own layer and those below it, never one above (imports inside functions
included), and nothing outside the command line (:data:`CLI`) imports it: the library and the benchmarks
stand without it.  Every project file is in exactly one layer.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

from pipeline.runtime.codeversion import PROJECT_PACKAGES, ROOT, module_name, module_path

#: The dependencies a module may import inside a function, and why.
LAZY = {
    "torch": "heavy (~1 s, ~300 MB at import): the torch-free core (params, methods, catalog, report, "
             "the CLI's --help) must not start it",
    "cv2": "imported after pipeline/__init__.py silences OpenCV's log; only image I/O needs it",
    "pandas": "heavy at import; the numeric core works on arrays",
    "pyarrow": "heavy at import; Parquet I/O only",
    "zarr": "Zarr I/O only",
    "scipy": "only some equations need it",
    "pydantic": "slow to import (~0.2 s): only code that validates params needs it",
    "matplotlib": "figures only (report, plots)",
    "ray": "optional: the cluster extra",
    "transformers": "optional: the sam3 extra (and heavy)",
    "onnx": "optional at run time: export and its benchmark only",
    "onnxruntime": "optional at run time: the ONNX engines only",
    "openvino": "optional: the openvino engine only",
    "dvclive": "optional: DVCLive logging only",
    "pycocotools": "the COCO writer only",
    "safetensors": "weights I/O only (with torch)",
}


#: The layers, lowest first: (name, what it holds, its files -- paths from the repository root, a folder
#: ending in "/").  A module imports its own layer and those below, never one above.
LAYERS = (
    ("core", "equations, tables and rules: params, methods, catalogue, DAG text; no artifact I/O",
     ("pipeline/runtime/", "pipeline/training/__init__.py", "pipeline/evaluation/__init__.py",
      "pipeline/orchestration/__init__.py", "pipeline/reproducibility.py", "pipeline/training/checkpointing.py",
      "pipeline/model.py", "pipeline/methods.py",
      "pipeline/training/filters.py",
      "pipeline/engine_table.py", "pipeline/teacher_table.py", "pipeline/params.py", "pipeline/profiles.py",
      "pipeline/catalog.py",
      "pipeline/stats.py", "pipeline/metrics.py", "pipeline/losses.py", "pipeline/geometry.py",
      "pipeline/augment.py", "pipeline/consensus.py", "pipeline/evaluation/diagnostics.py", "pipeline/orchestration/dag.py")),
    ("artifacts", "typed artifacts and files: Zarr/Parquet I/O, weights, streaming, results, ownership",
     ("pipeline/__init__.py", "pipeline/artifacts/", "pipeline/training/streaming.py",
      "pipeline/report/offline_plots.py", "pipeline/report/dvc_results.py", "pipeline/artifacts/provenance.py",
      "pipeline/thresholds.py")),  # tau calibration, and the tau candidates read from a thresholds table
    ("stage logic", "each stage's and tool's work, callable and tested without the CLI",
     ("pipeline/datasets/", "pipeline/datasets/prepare.py", "pipeline/teachers/", "pipeline/pseudo_labels.py",
      "pipeline/training/inputs.py", "pipeline/training/schedule.py", "pipeline/training/averaging.py",
      "pipeline/training/settings.py", "pipeline/training/self_training.py", "pipeline/training/loop.py", "pipeline/training/budget.py",
      "pipeline/training/seeds.py",
      "pipeline/evaluation/inference.py",
      "pipeline/evaluation/evaluate.py", "pipeline/deploy/export.py", "pipeline/deploy/image_files.py", "pipeline/deploy/",
      "pipeline/report/", "pipeline/cluster/", "pipeline/labeling/", "pipeline/review/")),
    ("api", "the Python API of the user tools: label, distill, a standalone project",
     ("pipeline/orchestration/standalone.py", "pipeline/api.py")),
    ("conventions", "what every command shares: the options, --params/--set/--device, one-line errors, logs",
     ("pipeline/cli/conventions.py",)),
    ("stages", "the DAG's stage scripts: options -> read artifacts -> call the logic -> write", ("stages/",)),
    ("commands", "the user commands and the geodistill click group over them and the stages", ("pipeline/cli/",)),
    ("benchmarks", "measurements and developer tools; they run the stages as commands, never import them",
     ("benchmarks/", "tools/")),
)
#: the command line, which no file outside it (the library, the benchmarks) imports
CLI = ("stages/", "pipeline/cli/")
#: the stage scripts, which nothing under the library's folder imports -- the user commands included: they
#: wire the library, and what they share with the commands lives in pipeline/cli/conventions.py
STAGE_SCRIPTS, LIBRARY = "stages/", "pipeline/"
#: the library's one package whose modules may run as scripts (``if __name__ == "__main__"``): the
#: command line; every other script is a benchmark or a tool (:data:`LAYERS`)
LIBRARY_SCRIPTS = ("pipeline/cli/",)


def layer_of(rel: str) -> int | None:
    """The index in :data:`LAYERS` of the file at ``rel`` (a POSIX path from the root); the longest
    matching entry decides (``pipeline/deploy/`` before a ``pipeline/`` one); None if none matches."""
    hits = [(len(entry), i) for i, (_, _, entries) in enumerate(LAYERS) for entry in entries
            if rel == entry or (entry.endswith("/") and rel.startswith(entry))]
    return max(hits)[1] if hits else None


def layer_violations(root: Path = ROOT) -> list[str]:
    """One line per file in no layer, per import of a higher layer, per import of the CLI from outside it, and
    per import of a stage script from under pipeline/."""
    bad = []
    for path in _files(root):
        rel = path.relative_to(root).as_posix()
        mine = layer_of(rel)
        if mine is None:
            bad.append(f"{rel} is in no layer: add it to LAYERS in tests/house/test_imports.py (docs/decisions.md, Layers)")
            continue
        top, lazy = _imports(path, root)
        for module, line in top + lazy:
            target = _project_file(module, root)
            if target is None or target == path:
                continue
            trel = target.relative_to(root).as_posix()
            theirs = layer_of(trel)
            if rel.startswith(LIBRARY) and trel.startswith(STAGE_SCRIPTS):
                bad.append(f"{rel}:{line} imports {module}: nothing under {LIBRARY} imports {STAGE_SCRIPTS} (what the "
                           "commands share with the stages lives in pipeline/cli/conventions.py)")
            elif not rel.startswith(CLI) and trel.startswith(CLI):
                bad.append(f"{rel}:{line} imports {module}: only the command line imports it ({', '.join(CLI)})")
            elif theirs is not None and theirs > mine:
                bad.append(f"{rel}:{line} ({LAYERS[mine][0]}) imports {module} ({LAYERS[theirs][0]}, a higher layer)")
    return bad


def _files(root: Path = ROOT) -> list[Path]:
    return sorted(p for pkg in PROJECT_PACKAGES for p in (root / pkg).rglob("*.py"))


def _targets(node: ast.AST, path: Path, root: Path) -> list[str]:
    """The modules an import statement names (relative imports resolved; ``from pkg import sub`` names
    ``pkg.sub`` when that is a project module)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if node.level:
        me = module_name(path, root)
        base = me.split(".") if path.name == "__init__.py" else me.split(".")[:-1]
        base = base[: len(base) - (node.level - 1)]
        module = ".".join(base + ([node.module] if node.module else []))
    else:
        module = node.module or ""
    subs = [f"{module}.{a.name}" for a in node.names if module_path(f"{module}.{a.name}", root) is not None]
    return subs if len(subs) == len(node.names) else [module] + subs


def _imports(path: Path, root: Path = ROOT) -> tuple[list[tuple[str, int]], list[tuple[str, int]]]:
    """(top-level imports, imports inside functions) of ``path`` as (module, line); those under ``if
    TYPE_CHECKING:`` run for a type checker only, never at run time, and are left out."""
    tree = ast.parse(path.read_text(), filename=str(path))
    inner: set[int] = set()
    typing_only: set[int] = set()
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            inner.update(id(n) for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom)))
        elif isinstance(fn, ast.If) and getattr(fn.test, "id", getattr(fn.test, "attr", None)) == "TYPE_CHECKING":
            typing_only.update(id(n) for stmt in fn.body for n in ast.walk(stmt))
    top, lazy = [], []
    for n in ast.walk(tree):
        if isinstance(n, (ast.Import, ast.ImportFrom)) and id(n) not in typing_only:
            (lazy if id(n) in inner else top).extend((m, n.lineno) for m in _targets(n, path, root))
    return top, lazy


def _project_file(module: str, root: Path = ROOT) -> Path | None:
    parts = module.split(".")
    for i in range(len(parts), 0, -1):  # ``from pipeline.x import name``: the longest module prefix
        p = module_path(".".join(parts[:i]), root)
        if p is not None:
            return p
    return None


def _heavy_deps(root: Path) -> dict[Path, set[str]]:
    """For each project file, the :data:`LAZY` dependencies that importing it starts: those it imports
    at its top, directly or through its own top-level project imports."""
    top = {p: _imports(p, root)[0] for p in _files(root)}
    deps = {p: {m.split(".")[0] for m, _ in imps} & set(LAZY) for p, imps in top.items()}
    changed = True
    while changed:
        changed = False
        for p, imps in top.items():
            for m, _ in imps:
                t = _project_file(m, root)
                if t is not None and not deps[t] <= deps[p]:
                    deps[p] |= deps[t]
                    changed = True
    return deps


def misplaced_imports(root: Path = ROOT) -> list[str]:
    """One line per import inside a function that the rule above does not allow."""
    deps = _heavy_deps(root)
    bad = []
    for path in _files(root):
        for module, line in _imports(path, root)[1]:
            dep = module.split(".")[0]
            where = f"{path.relative_to(root)}:{line} imports {module} inside a function"
            if dep in PROJECT_PACKAGES:
                target = _project_file(module, root)
                if target is None or not deps[target] - deps[path]:
                    bad.append(where + " (it starts no LAZY dependency this module does not already start: "
                                       "import it at the top)")
            elif dep in sys.stdlib_module_names or dep not in LAZY:
                bad.append(where + f" ({dep} is not in LAZY: import it at the top)")
    return bad


def import_circles(root: Path = ROOT) -> list[str]:
    """Each circle of the project's import graph (imports inside functions included) as a line."""
    graph: dict[Path, set[Path]] = {}
    for path in _files(root):
        top, lazy = _imports(path, root)
        graph[path] = {t for m, _ in top + lazy if (t := _project_file(m, root)) is not None and t != path}
    state: dict[Path, int] = {}
    cycles: list[list[str]] = []

    def visit(node: Path, stack: list[Path]) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                cyc = stack[stack.index(nxt):] + [nxt]
                cycles.append([str(p.relative_to(root)) for p in cyc])
            elif nxt not in state:
                visit(nxt, stack)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [])
    # a package's __init__ importing its own submodule is the package's face, not a circle
    real = [c for c in cycles if not any(a.endswith("__init__.py") and Path(b).parent == Path(a).parent
                                         for a, b in zip(c, c[1:]))]
    return [" -> ".join(c) for c in real]


def test_imports_sit_at_module_top_unless_lazy_for_a_reason():
    bad = misplaced_imports()
    assert not bad, "\n".join(bad)


def test_the_import_graph_has_no_circles():
    circles = import_circles()
    assert not circles, "\n".join(circles)


def test_the_checks_see_a_circle_and_a_misplaced_import(tmp_path):
    """Both checks can fail: in a small tree, a stdlib and a light project module imported inside a
    function, a heavy one imported lazily from a light module (allowed), and two modules importing
    each other."""
    pkg = tmp_path / "pipeline"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "heavy.py").write_text("import torch\n")
    (pkg / "a.py").write_text("def f():\n    import json\n    from pipeline import b\n    from pipeline import heavy\n")
    (pkg / "b.py").write_text("from pipeline import a\n")
    bad = misplaced_imports(tmp_path)
    assert [line.split(" (")[0] for line in bad] == ["pipeline/a.py:2 imports json inside a function",
                                                   "pipeline/a.py:3 imports pipeline.b inside a function"]
    assert import_circles(tmp_path) == ["pipeline/a.py -> pipeline/b.py -> pipeline/a.py"]


def test_every_module_is_in_a_layer_and_imports_none_above_it():
    bad = layer_violations()
    assert not bad, "\n".join(bad)


def test_the_layer_check_sees_an_upward_import_the_cli_and_an_unplaced_file(tmp_path):
    """The layer check can fail: in a small tree, a core module importing the API (a lazy import too),
    a benchmark importing a stage script, a user command importing a stage script (a lazy import too),
    and a module no layer lists; a stage importing the core and the API importing the core pass."""
    files = {"pipeline/__init__.py": "", "pipeline/params.py": "def f():\n    from pipeline import api\n",
             "pipeline/api.py": "from pipeline import params\n", "benchmarks/__init__.py": "",
             "benchmarks/bench_x.py": "import stages.prepare\n", "pipeline/unlisted.py": "",
             "pipeline/cli/__init__.py": "",
             "pipeline/cli/label.py": "from stages.prepare import f\ndef g():\n    import stages.prepare\n",
             "stages/__init__.py": "", "stages/prepare.py": "from pipeline.params import f\n"}
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    assert layer_violations(tmp_path) == [
        "benchmarks/bench_x.py:1 imports stages.prepare: only the command line imports it (stages/, pipeline/cli/)",
        *(f"pipeline/cli/label.py:{n} imports stages.prepare: nothing under pipeline/ imports stages/ (what the "
          "commands share with the stages lives in pipeline/cli/conventions.py)" for n in (1, 3)),
        "pipeline/params.py:2 (core) imports pipeline.api (api, a higher layer)",
        "pipeline/unlisted.py is in no layer: add it to LAYERS in tests/house/test_imports.py (docs/decisions.md, Layers)"]


def _is_main_block(node: ast.AST) -> bool:
    """``if __name__ == "__main__":`` (either operand order)."""
    if not (isinstance(node, ast.If) and isinstance(node.test, ast.Compare) and len(node.test.ops) == 1
            and isinstance(node.test.ops[0], ast.Eq)):
        return False
    sides = [node.test.left, *node.test.comparators]
    return {getattr(s, "id", None) for s in sides} >= {"__name__"} and any(
        isinstance(s, ast.Constant) and s.value == "__main__" for s in sides)


def library_scripts(root: Path = ROOT) -> list[str]:
    """Each module under pipeline/, outside :data:`LIBRARY_SCRIPTS`, with a ``__main__`` block."""
    return [f"{rel}:{node.lineno} runs as a script: move it to benchmarks/ or tools/ (the library's only "
            f"scripts are the command line, {', '.join(LIBRARY_SCRIPTS)})"
            for path in sorted((root / "pipeline").rglob("*.py"))
            if not (rel := path.relative_to(root).as_posix()).startswith(LIBRARY_SCRIPTS)
            for node in ast.parse(path.read_text(), filename=str(path)).body if _is_main_block(node)]


def test_no_module_of_the_library_but_the_command_line_runs_as_a_script():
    bad = library_scripts()
    assert not bad, "\n".join(bad)


def test_the_script_check_sees_a_main_block_in_the_library_only(tmp_path):
    main = 'if __name__ == "__main__":\n    main()\n'
    files = {"pipeline/__init__.py": "", "pipeline/tool.py": "def main(): ...\n" + main,
             "pipeline/flipped.py": "if '__main__' == __name__:\n    pass\n",
             "pipeline/name_only.py": "if __name__ == 'pipeline.name_only':\n    pass\n",
             "pipeline/cli/__init__.py": main, "benchmarks/bench_x.py": main}
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    assert [line.split(" ")[0] for line in library_scripts(tmp_path)] == ["pipeline/flipped.py:1", "pipeline/tool.py:2"]


def test_the_torch_free_core_imports_without_torch():
    """Importing the params schema, the recipes and the catalogue (what ``--help`` and the DAG text read) starts no
    torch, in a fresh process: package ``__init__`` files stay light (issue 64)."""
    import os
    import subprocess

    code = "import sys, pipeline.params, pipeline.methods, pipeline.catalog; print('torch' in sys.modules)"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "False"


def test_the_file_reader_calls_no_other_datasets_module():
    """pipeline/datasets/loading.py is where prepare's rows become arrays: the header, the decode and the cache in
    one room.  A call from it into another pipeline/datasets module and back (the header reader was one) is a
    return on prepare's data flow (`farm-studio walk pipeline/datasets/prepare.py:prepare:cfg`: 0 returns)."""
    path = ROOT / "pipeline/datasets/loading.py"
    top, lazy = _imports(path)
    assert [m for m, _ in top + lazy if m.startswith("pipeline.datasets")] == []
