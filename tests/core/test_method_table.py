"""The method table is the one source of method facts: labels, roles, ablation tables, gain reference
points and table order live in pipeline.methods.METHODS, everything else derives from it, and no other
module of pipeline/ or stages/ spells a method's name (torch-free)."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest

from pipeline import methods as M
from pipeline.methods import METHODS, Method

ROOT = Path(__file__).resolve().parents[2]
#: where a method's name may be written: the table itself and the profiles' choice of runs
ALLOWED = {"pipeline/methods.py", "pipeline/profiles.py"}


def _program_name(node: ast.AST, path: str) -> bool:
    """The one string equal to a method name by coincidence: the program's name (pipeline.artifacts.lineage.PROGRAM)."""
    return path == "pipeline/artifacts/lineage.py" and isinstance(node, ast.Assign) and \
        [getattr(t, "id", None) for t in node.targets] == ["PROGRAM"]


def method_name_literals() -> list[str]:
    """``path:line: name`` of every string constant equal to a method name in pipeline/ and stages/,
    outside :data:`ALLOWED` (an AST scan: comments and docstrings that mention a name among other
    words are not string constants equal to it)."""
    hits = []
    for folder in ("pipeline", "stages"):
        for file in sorted((ROOT / folder).rglob("*.py")):
            rel = file.relative_to(ROOT).as_posix()
            if rel in ALLOWED:
                continue
            tree = ast.parse(file.read_text(), rel)
            exempt = {id(c) for n in ast.walk(tree) if _program_name(n, rel) for c in ast.walk(n)}
            hits += [f"{rel}:{n.lineno}: {n.value!r}" for n in ast.walk(tree)
                     if isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value in METHODS
                     and id(n) not in exempt]
    return hits


def test_no_module_but_the_table_and_the_profiles_spells_a_method_name():
    hits = method_name_literals()
    assert not hits, "method names outside pipeline/methods.py (use its roles and constants):\n" + "\n".join(hits)


def test_the_scan_sees_a_method_name_where_one_is_written(tmp_path, monkeypatch):
    """The scan is not blind: a module that writes a method's name is reported."""
    bad = ROOT / "pipeline" / "_scan_probe.py"
    monkeypatch.setattr(Path, "rglob", lambda self, pattern: iter([bad]) if self.name == "pipeline" else iter([]))
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: f"X = {M.PROPOSED!r}\n")
    assert method_name_literals() == [f"pipeline/_scan_probe.py:1: {M.PROPOSED!r}"]


def test_study_facts_are_complete_and_unique():
    M.check_method_table(METHODS)
    assert all(m.label for m in METHODS.values())
    for bad in (dict(role="baseline"), dict(ablation_tables=("nope",)), dict(reference_for="all"),
                dict(label=""), dict(role="ablation", ablation_tables=())):
        fields = {"name": "x", "label": "x", "table_order": -1, **bad}
        table = {**METHODS, "x": dataclasses.replace(METHODS[M.PROPOSED], **fields)}
        with pytest.raises(ValueError, match="'x'"):
            M.check_method_table(table)
    twin = {**METHODS, "x": dataclasses.replace(METHODS[M.BASELINE], name="x", table_order=-1)}
    with pytest.raises(ValueError, match="label"):
        M.check_method_table(twin)
    with pytest.raises(ValueError, match="exactly one proposed method"):
        M.the_method("proposed method", lambda m: m.role == "proposed",
                     {**METHODS, "x": dataclasses.replace(METHODS[M.PROPOSED], name="x")})


def test_roles_give_the_paper_protocol_and_the_report_tables():
    from pipeline import profiles
    from pipeline.report import tables as T

    by_role = lambda *r: [n for n, m in METHODS.items() if m.role in r]  # noqa: E731
    assert profiles.MAIN_METHODS == by_role("main", "proposed") and len(profiles.MAIN_METHODS) == 5
    assert profiles.ABLATIONS == by_role("ablation") and len(profiles.ABLATIONS) == 7
    assert profiles.CONTROLS == by_role("control") and M.SUPERVISED_CEILING in profiles.CONTROLS
    # gains: the baseline covers every annotation-free method, the continuation the warm-started ones
    assert M.GAIN_CONTROLS == (M.BASELINE, M.CONTINUATION)
    assert METHODS[M.STAGE_ONE].stage == 1 and METHODS[M.PROPOSED].init == "stage1"
    # the report's orders are the table order; every row of an ablation table names it
    order = [METHODS[m].table_order for m in T.MAIN_ORDER]
    assert order == sorted(order) and T.MAIN_ORDER[0] == M.BASELINE and M.PROPOSED in T.MAIN_ORDER
    assert M.SUPERVISED_CEILING not in T.MAIN_ORDER and not T.ABLATIONS & set(T.MAIN_ORDER)
    for rows, table in ((T.WARM_START_ROWS, "warm_start"), (T.COMPONENT_ROWS, "component")):
        assert all(table in METHODS[m].ablation_tables for m in rows) and rows[-1] == M.PROPOSED
    assert T.WARM_START_ROWS[0] == M.BASELINE and T.ABLATIONS == set(profiles.ABLATIONS)
    assert T.label(M.PROPOSED) == METHODS[M.PROPOSED].label and T.label("unknown") == "unknown"


def test_a_new_method_is_one_row(monkeypatch):
    """A row added to the table appears in its role's lists, its ablation table (at its table order),
    its gains and its label -- nothing else to edit."""
    row = Method("sdf_only_gated_late", 2, "stage1", ("epochs_stage2",), "lr_stage2", terms=("region", "sdf"),
                 select="stage2", label="Gated SDF, late", role="ablation", ablation_tables=("component",),
                 table_order=METHODS["sdf_area_gated"].table_order + 1, color="#123456", symbol="1", dash="dashed")
    monkeypatch.setitem(METHODS, row.name, row)
    M.check_method_table(METHODS)
    assert row.name in M.methods_with_role("ablation")
    rows = M.ablation_table_rows("component")
    assert rows.index(row.name) == rows.index("sdf_area_gated") + 1
    assert row.name in M.gain_treatments(M.CONTINUATION, list(METHODS))
    assert M.method_label(row.name) == "Gated SDF, late"


def test_every_recipe_part_is_in_every_runs_fingerprint():
    """A recipe part changes what a run trains: a run's fingerprint (the DAG's rerun key) must hold it."""
    from pipeline.methods import METHODS, param_keys
    from pipeline.params import recipe_parts

    train_parts = [p for p in recipe_parts() if p.startswith("train.")]
    assert len(train_parts) > 10
    for m in METHODS.values():  # the epochs parts: those the method trains for
        missing = [p for p in train_parts if p not in param_keys(m) and not p.startswith("train.epochs_stage")]
        assert missing == [], m.name
