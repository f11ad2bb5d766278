"""The catalogue owns every artifact file name (pipeline.catalog), and the deploy bundle's layout is one
table that its writer, its readers and the engine registry use.

The AST scan flags, in pipeline/ and stages/, a string constant that is a catalogued file name (or a path
ending in one: ``"artifacts/manifest.parquet"``), or a path-like string (no spaces) ending in a catalogued
suffix (``.parquet``, ``.zarr``, the suffixes of the schema'd artifacts).  Prose (help texts, messages,
docstrings) has spaces and is not a file name.  :data:`ALLOWED` names the exceptions, each with its reason.
"""

from __future__ import annotations

import ast
from pathlib import Path, PurePosixPath

import pytest

from pipeline import catalog
from pipeline.codeversion import ROOT
from pipeline.engine_table import ENGINE_CHOICES, ENGINE_TABLE, MODEL_ENGINES, SEGMENT_ENGINES

#: the module that owns the file names
OWNERS = ("pipeline/catalog.py",)

#: (file, string) -> why that literal is not a catalogue lookup
ALLOWED = {
    ("pipeline/artifacts.py", ".parquet"): "open_artifact dispatches on the file format's suffix",
    ("pipeline/artifacts.py", ".zarr"): "open_artifact dispatches on the file format's suffix",
    ("pipeline/training.py", "/anchor.zarr"): "a scratch spill file in a temporary folder, not an artifact",
    ("benchmarks/bench_memory.py", ".zarr"): "the memory benchmark's own scratch arrays, not artifacts",
    ("pipeline/teachers/imported.py", "scores.parquet"): "the imported teacher's input layout (files a user brings)",
    ("pipeline/teachers/imported.py", ".parquet"): "the imported teacher's scores file: Parquet or CSV by suffix",
    ("pipeline/labeling/writing.py", "labels.parquet"): "the label command's own output table (pipeline.labeling.writing.OUTPUTS)",
    ("pipeline/labeling/writing.py", "contact_sheet.png"): "the label command's own output table (pipeline.labeling.writing.OUTPUTS)",
}


def catalogued_names() -> set[str]:
    """Every file name the catalogue owns: the artifacts' file names (a folder name is a word, not a
    file name), the checkpoint's and the deploy bundle's files."""
    names = {PurePosixPath(a.path).name for a in catalog.ARTIFACTS.values()}
    names = {n for n in names if "." in n and "{" not in n}
    return names | {f.name for f in catalog.DEPLOY_BUNDLE.values()} | {
        catalog.WEIGHTS_FILE, catalog.WEIGHTS_CONFIG_FILE, catalog.LEGACY_WEIGHTS_FILE, catalog.TRAINING_LOG_FILE}


def catalogued_suffixes() -> set[str]:
    """The suffixes of the artifacts with a schema (the formats open_artifact reads)."""
    return {PurePosixPath(a.path).suffix for a in catalog.ARTIFACTS.values() if a.schema} - {""}


def flagged(source: str, names=None, suffixes=None) -> list[tuple[int, str]]:
    """(line, string) of every string constant in ``source`` that spells a catalogued file name."""
    names = catalogued_names() if names is None else names
    suffixes = catalogued_suffixes() if suffixes is None else suffixes
    out = []
    for node in ast.walk(ast.parse(source)):
        if not (isinstance(node, ast.Constant) and isinstance(node.value, str)):
            continue
        s = node.value
        if any(c.isspace() for c in s) or not s:
            continue
        if PurePosixPath(s).name in names or s.endswith(tuple(suffixes)):
            out.append((node.lineno, node.col_offset, s))
    return [(line, s) for line, _, s in sorted(out)]


def _sources() -> list[Path]:
    return sorted(p for pkg in ("pipeline", "stages") for p in (ROOT / pkg).rglob("*.py"))


def test_the_scanner_flags_names_suffixes_and_paths_but_not_prose():
    src = '''
"""Docstring naming manifest.parquet and model.onnx in prose."""
a = "manifest.parquet"
b = root / "model.onnx"
c = f"{name}.zarr"
d = "artifacts/teacher.zarr"
e = "a folder holding manifest.parquet, images.zarr"
f = "teacher"
g = "deploy.json"
'''
    hits = [s for _, s in flagged(src)]
    assert hits == ["manifest.parquet", "model.onnx", ".zarr", "artifacts/teacher.zarr", "deploy.json"]
    assert flagged('x = "other.zarr"', names=set(), suffixes={".parquet"}) == []


def test_no_file_name_literal_outside_the_catalogue():
    found = []
    for path in _sources():
        rel = path.relative_to(ROOT).as_posix()
        if rel in OWNERS:
            continue
        found += [f"{rel}:{line}: {s!r}" for line, s in flagged(path.read_text()) if (rel, s) not in ALLOWED]
    assert not found, "file names spelled outside pipeline/catalog.py (use catalog.path / the layout tables):\n" \
        + "\n".join(found)


@pytest.mark.parametrize("entry", sorted(ALLOWED))
def test_every_allowlist_entry_is_still_needed(entry):
    rel, s = entry
    assert ALLOWED[entry].strip(), f"{entry}: no reason given"
    assert s in [hit for _, hit in flagged((ROOT / rel).read_text())], f"{entry}: no longer in {rel}; drop it"


def test_the_bundle_layout_is_one_table_that_the_writer_readers_and_engines_use():
    from pipeline.artifacts import get_schema
    from pipeline.deploy import bundle, engines

    layout = catalog.DEPLOY_BUNDLE
    # the writer's and the readers' names are the table's
    assert (bundle.DEPLOY_JSON, bundle.TORCHSCRIPT_FILE, bundle.ONNX_FILE, bundle.INT8_FILE) == tuple(
        layout[k].name for k in ("deploy_json", "torchscript", "onnx", "int8"))
    # every engine reads one file of the table, and the registry runs exactly that file
    for name, spec in ENGINE_TABLE.items():
        assert spec.reads in layout, name
        assert engines.ENGINES[name].needs == ("model" if spec.reads == "weights" else layout[spec.reads].name)
        assert name in catalog.bundle_readers(spec.reads)
    assert set(catalog.bundle_readers("int8")) == {"onnxruntime_int8", "openvino_int8"}
    # the deploy schema checks the table's required files
    required = {f.name for f in layout.values() if f.required}
    files = get_schema("deploy").files
    assert {bundle.DEPLOY_JSON, bundle.TORCHSCRIPT_FILE} <= set(files) and required - set(files) <= {
        catalog.WEIGHTS_FILE, catalog.WEIGHTS_CONFIG_FILE}


def test_engine_names_are_one_list():
    from pipeline.deploy.engines import ENGINES
    from pipeline.params import BENCHMARK_VARIANTS, PAPER

    assert list(ENGINES) == list(ENGINE_TABLE)
    assert ENGINE_CHOICES == ("auto", *SEGMENT_ENGINES) and set(MODEL_ENGINES) <= set(SEGMENT_ENGINES)
    assert PAPER.deploy.benchmark_variants == BENCHMARK_VARIANTS == [n for n, e in ENGINE_TABLE.items() if e.benchmark]
