"""A recipe part is declared once (issue 64 item 2): a throwaway part added to ``pipeline.methods.PARTS`` alone (one
file) reaches the schema, every recipe, the fingerprint keys, the departure labels, ``Settings`` and params.yaml."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

DECLARATION = '''    RecipePart("train.throwaway_gain", float, 1.0, "a throwaway lever of the test", {"gt": 0, "le": 2},
               departure="throwaway gain {v:g}", stage_one=True, home="settings"),
'''

PROBE = r'''
import dataclasses, json
from pipeline.methods import COMMON_KEYS, DEPARTURES, METHODS, RECIPES, departures, get_method, param_keys
from pipeline.params import PAPER, TrainParams, validate_section
from pipeline.orchestration.dag import render_params_yaml
from pipeline.runtime.errors import InputError
from pipeline.training.settings import Settings

cfg = PAPER.train.model_dump()
field = TrainParams.model_fields["throwaway_gain"]
try:
    validate_section("train", {**cfg, "throwaway_gain": 3.0})
    refused = ""
except InputError as e:
    refused = str(e)
stage1 = Settings.from_params(get_method("plain"), {**cfg, "throwaway_gain": 0.5}, 0.5)
stage2 = Settings.from_params(get_method("geodistill"), {**cfg, "throwaway_gain": 0.5}, 0.5)
print(json.dumps({
    "description": field.description, "default": field.default,
    "recipes": {r: v["train"]["throwaway_gain"] for r, v in RECIPES.items()},
    "paper_value": PAPER.train.throwaway_gain, "refused": refused,
    "common": "throwaway_gain" in COMMON_KEYS, "last_common": COMMON_KEYS[-1],
    "fingerprinted": all("train.throwaway_gain" in param_keys(m) for m in METHODS.values()),
    "departure": departures({"train.throwaway_gain": 0.5}), "no_departure": departures({"train.throwaway_gain": 1.0}),
    "in_departures": "train.throwaway_gain" in DEPARTURES,
    "stage1": stage1.throwaway_gain, "stage2": stage2.throwaway_gain,
    "documented": "throwaway_gain : float" in Settings.__doc__,
    "params_yaml": [ln for ln in render_params_yaml("demo").splitlines() if "throwaway_gain" in ln],
}))
'''


def test_a_part_declared_in_one_place_reaches_every_derived_list(tmp_path):
    shutil.copytree(REPO / "pipeline", tmp_path / "pipeline", ignore=shutil.ignore_patterns("__pycache__"))
    methods = tmp_path / "pipeline" / "methods.py"
    text = methods.read_text()
    anchor = '    RecipePart("calibrate.tau_rule"'
    assert text.count(anchor) == 1, "the test inserts its part before the calibrate part"
    methods.write_text(text.replace(anchor, DECLARATION + anchor))
    changed = [p.relative_to(tmp_path).as_posix() for p in (tmp_path / "pipeline").rglob("*.py")
               if p.read_bytes() != (REPO / p.relative_to(tmp_path)).read_bytes()]
    assert changed == ["pipeline/methods.py"]

    out = subprocess.run([sys.executable, "-c", PROBE], cwd=tmp_path, capture_output=True, text=True,
                         env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(tmp_path)}, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["description"] == "recipe part, Stage I: a throwaway lever of the test"
    assert got["default"] is None and got["paper_value"] == 1.0
    assert set(got["recipes"].values()) == {1.0} and set(got["recipes"]) >= {"paper", "stable", "progressive"}
    assert "throwaway_gain=3.0" in got["refused"] and "less than or equal to 2" in got["refused"]
    assert got["common"] and got["last_common"] == "throwaway_gain" and got["fingerprinted"]
    assert got["in_departures"] and got["departure"] == ["throwaway gain 0.5"] and got["no_departure"] == []
    assert got["stage1"] == 0.5 and got["stage2"] == 1.0  # a Stage-I part is off outside Stage I
    assert got["documented"]
    assert got["params_yaml"] == ["  throwaway_gain: null  # recipe part, Stage I: a throwaway lever of the test"]


def test_the_declarations_reproduce_the_recipes_and_orders():
    """The derived lists equal what they were before the declaration existed (params.yaml, dvc.yaml unchanged)."""
    from pipeline.methods import COMMON_KEYS, PARTS, RECIPES, recipe_parts
    from pipeline.params import TrainParams

    assert recipe_parts()[-1] == "calibrate.tau_rule" and len(recipe_parts()) == len(PARTS)
    assert RECIPES["progressive"]["train"]["low_res_fraction"] == 8 / 11
    assert RECIPES["stable"]["train"]["precision"] == "fp32" and RECIPES["paper"]["train"]["precision"] == "auto"
    order = list(TrainParams.model_fields)
    assert order.index("batch_size") == order.index("precise_bn") + 1
    assert order.index("until") == order.index("validate_low_res") + 1
    assert COMMON_KEYS.index("bootstrap_beta") == COMMON_KEYS.index("validate_low_res") + 1
    assert "epochs_stage1" not in COMMON_KEYS  # a method's own epochs (Method.epochs)
