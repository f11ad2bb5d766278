"""The catalogue owns every output file name (pipeline.catalog), and the deploy bundle's layout is one
table that its writer, its readers and the engine registry use.

The AST scan flags, in pipeline/ and stages/, a string constant that is a catalogued file name (or a path
ending in one: ``"artifacts/manifest.parquet"``), a path-like string (no spaces) ending in a catalogued
suffix (``.parquet``, ``.zarr``, the suffixes of the schema'd artifacts), or any other file name with an
output extension (:data:`OUTPUT_EXTENSIONS`; a bare suffix such as ``".png"`` is a format, not a name).
Prose (help texts, messages, docstrings) has spaces and is not a file name.  :data:`ALLOWED` and
:data:`INPUTS` name the exceptions, each with its reason.
"""

from __future__ import annotations

import ast
from pathlib import Path, PurePosixPath

import pytest

from pipeline import catalog
from pipeline.runtime.codeversion import ROOT
from pipeline.engine_table import ENGINE_CHOICES, ENGINE_TABLE, MODEL_ENGINES, SEGMENT_ENGINES

#: the module that owns the file names
OWNERS = ("pipeline/catalog.py",)

#: (file, string) -> why that literal is not a catalogue lookup
ALLOWED = {
    ("pipeline/artifacts/store.py", ".parquet"): "open_artifact dispatches on the file format's suffix",
    ("pipeline/artifacts/store.py", ".zarr"): "open_artifact dispatches on the file format's suffix",
    ("pipeline/training/loop.py", "/anchor.zarr"): "a scratch spill file in a temporary folder, not an artifact",
    ("benchmarks/bench_memory.py", ".zarr"): "the memory benchmark's own scratch arrays, not artifacts",
    ("pipeline/teachers/imported.py", "scores.parquet"): "the imported teacher's input layout (files a user brings)",
    ("pipeline/teachers/imported.py", ".parquet"): "the imported teacher's scores file: Parquet or CSV by suffix",
    ("pipeline/params.py", "params.yaml"): "DEFAULT_PARAMS: the catalogue imports params.py (catalog.PARAMS_FILE)",
    ("pipeline/teachers/imported.py", "scores.csv"): "the imported teacher's scores file: Parquet or CSV",
    ("pipeline/datasets/loading.py", ".tmp.npz"): "the decode cache's temporary name before its atomic rename",
    ("pipeline/cli/plots.py", "page.html"): "a scratch page in a temporary folder that dvc plots reads",
    ("pipeline/deploy/benchmark.py", "model_int8.onnx"): "the benchmark's scratch int8 model in its temporary folder",
    ("pipeline/deploy/quantize.py", "pre.onnx"): "a scratch file in a temporary folder",
    ("pipeline/deploy/quantize.py", "augmented.onnx"): "a scratch file in a temporary folder",
    ("pipeline/deploy/quantize.py", "x.npy"): "a scratch file in a temporary folder",
    ("pipeline/deploy/quantize.py", "z.npy"): "a scratch file in a temporary folder",
}

#: file names the project reads but never writes as an output -> why
INPUTS = {
    "config.json": "SAM 3's checkpoint (pipeline.teachers.sam3; tiny_sam3 writes a stand-in)",
    "tokenizer.json": "SAM 3's checkpoint",
    "vocab.json": "SAM 3's checkpoint",
    "merges.txt": "SAM 3's checkpoint",
    "preprocessor_config.json": "SAM 3's checkpoint",
    "processor_config.json": "SAM 3's checkpoint",
    "checkpoint_hashes.json": "the SAM 3 cache's hash memo, beside the user's checkpoint cache",
    "lock.txt": "the repository's requirements lock (the Makefile writes it)",
    "spacesense_bench.yaml": "a dataset protocol in data_manifests/",
    "spark.yaml": "a dataset protocol in data_manifests/",
    "speedplus.yaml": "a dataset protocol in data_manifests/",
    "tango.yaml": "a dataset protocol in data_manifests/",
    "folder.yaml": "a dataset protocol in data_manifests/",
}

#: the extensions of the files the project writes
OUTPUT_EXTENSIONS = (".json", ".parquet", ".zarr", ".png", ".svg", ".csv", ".tsv", ".txt", ".log", ".html", ".md",
                     ".xml", ".onnx", ".ts", ".npy", ".npz", ".pt", ".safetensors", ".yaml", ".yml")


def catalogued_names() -> set[str]:
    """Every file name the catalogue owns: the artifacts' file names (a folder name is a word, not a
    file name), the checkpoint's and the deploy bundle's files."""
    names = {PurePosixPath(a.path).name for a in catalog.ARTIFACTS.values()}
    names = {n for n in names if "." in n and "{" not in n}
    outputs = {f.name for files in catalog.OUTPUT_FILES.values() for f in files.values()}
    return names | {f.name for f in catalog.DEPLOY_BUNDLE.values()} | {n for n in outputs if "." in n and "{" not in n} | {
        catalog.WEIGHTS_FILE, catalog.WEIGHTS_CONFIG_FILE, catalog.LEGACY_WEIGHTS_FILE, catalog.TRAINING_LOG_FILE,
        catalog.META_FILE, catalog.RESUME_STATE_FILE, catalog.DVC_FILE, catalog.PARAMS_FILE}


def catalogued_suffixes() -> set[str]:
    """The suffixes of the artifacts with a schema (the formats open_artifact reads)."""
    return {PurePosixPath(a.path).suffix for a in catalog.ARTIFACTS.values() if a.schema} - {""}


def looks_like_output_name(s: str, extensions=OUTPUT_EXTENSIONS) -> bool:
    """A file name (or a path ending in one) with an output extension: not a bare suffix, a glob or a URL."""
    name = PurePosixPath(s).name.lower()
    return "*" not in s and "://" not in s and name.endswith(tuple(extensions)) and name not in extensions


def flagged(source: str, names=None, suffixes=None, extensions=OUTPUT_EXTENSIONS) -> list[tuple[int, str]]:
    """(line, string) of every string constant in ``source`` that spells a catalogued file name or looks
    like an output file name."""
    names = catalogued_names() if names is None else names
    suffixes = catalogued_suffixes() if suffixes is None else suffixes
    out = []
    for node in ast.walk(ast.parse(source)):
        if not (isinstance(node, ast.Constant) and isinstance(node.value, str)):
            continue
        s = node.value
        if any(c.isspace() for c in s) or not s:
            continue
        if PurePosixPath(s).name in names or s.endswith(tuple(suffixes)) or looks_like_output_name(s, extensions):
            out.append((node.lineno, node.col_offset, s))
    return [(line, s) for line, _, s in sorted(out)]


def _sources(root: Path = ROOT) -> list[Path]:
    return sorted(p for pkg in ("pipeline", "stages") for p in (root / pkg).rglob("*.py"))


def violations(root: Path = ROOT) -> list[str]:
    """``file:line: 'name'`` of every flagged literal under ``root`` that no allowlist excuses."""
    found = []
    for path in _sources(root):
        rel = path.relative_to(root).as_posix()
        if rel in OWNERS:
            continue
        found += [f"{rel}:{line}: {s!r}" for line, s in flagged(path.read_text())
                  if (rel, s) not in ALLOWED and PurePosixPath(s).name not in INPUTS]
    return found


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
    assert flagged('x = "other.zarr"', names=set(), suffixes={".parquet"}, extensions=()) == []


def test_the_scanner_flags_uncatalogued_output_names_but_not_suffixes_globs_or_urls():
    src = '''
a = out / "summary_v2.json"
b = open(f"{out}/scores.tsv", "w")
c = f"{stem}.png"
d = sorted(folder.glob("*.json"))
e = "https://example.org/schema.json"
f = "figures/new_plot.svg"
'''
    assert [s for _, s in flagged(src)] == ["summary_v2.json", "/scores.tsv", "figures/new_plot.svg"]


def test_the_check_catches_a_planted_output_name(tmp_path):
    (tmp_path / "pipeline").mkdir()
    (tmp_path / "pipeline" / "writer.py").write_text('def w(out):\n    (out / "planted.json").write_text("{}")\n')
    (tmp_path / "stages").mkdir()
    (tmp_path / "stages" / "reader.py").write_text('import json\nx = json.loads(open("config.json").read())\n')
    assert violations(tmp_path) == ["pipeline/writer.py:2: 'planted.json'"]


def test_no_file_name_literal_outside_the_catalogue():
    found = violations()
    assert not found, "file names spelled outside pipeline/catalog.py (use catalog.path / the layout tables):\n" \
        + "\n".join(found)


@pytest.mark.parametrize("entry", sorted(ALLOWED))
def test_every_allowlist_entry_is_still_needed(entry):
    rel, s = entry
    assert ALLOWED[entry].strip(), f"{entry}: no reason given"
    assert s in [hit for _, hit in flagged((ROOT / rel).read_text())], f"{entry}: no longer in {rel}; drop it"


@pytest.mark.parametrize("name", sorted(INPUTS))
def test_every_input_name_is_still_read(name):
    assert INPUTS[name].strip() and name not in catalogued_names(), f"{name}: no reason given, or catalogued"
    assert any(PurePosixPath(s).name == name for p in _sources() for _, s in flagged(p.read_text())), \
        f"{name}: no longer in pipeline/ or stages/; drop it"


def test_the_bundle_layout_is_one_table_that_the_writer_readers_and_engines_use():
    from pipeline.artifacts.schemas import get_schema
    from pipeline.deploy import bundle, engines

    layout = catalog.DEPLOY_BUNDLE
    # the writer's and the readers' names are the table's
    assert (bundle.DEPLOY_JSON, bundle.TORCHSCRIPT_FILE, bundle.ONNX_FILE, bundle.INT8_FILE) == tuple(
        layout[k].name for k in ("deploy_json", "torchscript", "onnx", "int8"))
    # every engine reads one file of the table, and the registry runs exactly that file
    for name, spec in ENGINE_TABLE.items():
        assert spec.reads in layout, name
        assert engines.ENGINES[name].needs == ("model" if spec.reads == "weights" else layout[spec.reads].name)
    assert {n for n, e in ENGINE_TABLE.items() if e.reads == "int8"} == {"onnxruntime_int8", "openvino_int8"}
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
