"""pipeline.thresholds.tau_candidates: the one function that gives a checkpoint's or a bundle's tau
candidates, calibrated and fixed (eq:inference-mask binarises with the one resolve_tau picks)."""

from __future__ import annotations

import pandas as pd
import pytest

from pipeline.artifacts.lineage import make_meta
from pipeline.artifacts.store import open_artifact, write_parquet
from pipeline.params import PAPER
from pipeline.thresholds import NO_VALIDATION_MASKS, resolve_tau, tau_candidates

PARAMS = {"calibrate": {"fixed_tau": 0.45}}


def _table(rows) -> pd.DataFrame:
    return pd.DataFrame(rows, columns=["method", "seed", "tau", "val_iou", "fixed_tau", "tau_source"])


TABLE = _table([["geodistill", 42, 0.62, 0.8, 0.5, None], ["plain", 1, 0.5, float("nan"), 0.5, NO_VALIDATION_MASKS]])


def test_a_bundle_gives_its_exported_tau_and_the_params_fixed_tau():
    taus = tau_candidates(bundle={"tau": 0.47, "tau_source": "calibrated"}, params=PARAMS)
    assert taus == {"bundle": (0.47, "deploy bundle (calibrated)"), "fixed": (0.45, "calibrate.fixed_tau")}
    assert resolve_tau(**taus) == (0.47, "deploy bundle (calibrated)")
    assert resolve_tau(option=0.3, **taus) == (0.3, "--tau")
    assert tau_candidates(bundle={"tau": None}) == {}                       # nothing recorded, no params


def test_a_checkpoint_payload_tau_wins_and_the_table_is_then_not_read(tmp_path):
    taus = tau_candidates(payload={"method": "geodistill", "seed": 42, "tau": 0.3},
                          thresholds=tmp_path / "absent_but_unread.parquet")
    assert taus == {"checkpoint": (0.3, "checkpoint payload")}


def test_a_checkpoint_gets_its_calibrated_row_and_the_fixed_tau_calibrate_recorded():
    taus = tau_candidates(payload={"method": "geodistill", "seed": 42}, thresholds=TABLE, params=PARAMS)
    assert taus["thresholds"] == (0.62, "calibrated on the validation split (thresholds table: geodistill, seed 42)")
    assert taus["fixed"][0] == 0.5            # the row's fixed_tau (what calibrate used), not the params' 0.45
    assert resolve_tau(**taus)[0] == 0.62
    # a row calibrate could not calibrate says so
    plain = tau_candidates(payload={"method": "plain", "seed": 1}, thresholds=TABLE)
    assert plain["thresholds"][1].startswith(NO_VALIDATION_MASKS)


def test_without_a_row_the_fixed_tau_comes_from_params_and_says_why(tmp_path):
    path = tmp_path / "thresholds.parquet"
    write_parquet(path, TABLE, make_meta("thresholds", "calibrate", "test", {}))
    for thresholds in (path, str(path), open_artifact(path, "thresholds")):   # a path or an opened artifact
        taus = tau_candidates(payload={"method": "geodistill", "seed": 7}, thresholds=thresholds, params=PARAMS)
        assert taus == {"fixed": (0.45, f"calibrate.fixed_tau (no calibrated row for geodistill seed 7 in {path})")}
    assert tau_candidates(payload={"method": "m", "seed": 1}, params=PARAMS) == \
        {"fixed": (0.45, "calibrate.fixed_tau (no --thresholds given)")}
    # a table path that does not exist is no table; without params there is no fixed tau at all
    assert tau_candidates(payload={"method": "m", "seed": 1}, thresholds=tmp_path / "none.parquet") == {}
    with pytest.raises(Exception, match="no calibrated tau"):
        resolve_tau(**tau_candidates(payload={"method": "m", "seed": 1}))
    # the schema's default params give the paper's fixed tau
    assert tau_candidates(payload={"method": "m", "seed": 1}, params=PAPER.model_dump())["fixed"][0] == \
        PAPER.calibrate.fixed_tau


def test_evaluation_takes_both_taus_from_the_one_function():
    from pipeline.runtime.errors import ArtifactError
    from pipeline.evaluation.evaluate import run_thresholds

    assert run_thresholds(TABLE, "geodistill", 42, "ckpt") == (0.62, 0.5)
    with pytest.raises(ArtifactError, match="no calibrated threshold for geodistill/7"):
        run_thresholds(TABLE, "geodistill", 7, "ckpt")
