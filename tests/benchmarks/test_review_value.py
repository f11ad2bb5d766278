"""The review-value benchmark at tiny size: the selections pick what they say, every (selection, k, seed)
trains and scores, and the table carries the gains, the ranking-minus-random rows and the caveat."""

from __future__ import annotations

import numpy as np

from benchmarks import review_value as rv
from tests.builders.training import tiny_cfg
from pipeline.training.checkpointing import NoCheckpointer


def test_selections_pick_the_lowest_gate_and_the_shipped_ranking(tiny):
    from pipeline.methods import get_method
    from pipeline.training.inputs import load_inputs

    data, _, _ = load_inputs(tiny, get_method("plain"), tiny_cfg())
    table = rv.training_table(tiny, list(data.image_ids))
    gate = rv.select(table, "gate", 2, np.random.default_rng(0))
    assert gate[0] == "img000" and set(gate) == set(table.nsmallest(2, "g")["image_id"])  # g[0] = 0 in tiny
    assert len(set(rv.select(table, "random", 3, np.random.default_rng(0)))) == 3
    assert rv.select(table, rv.DEFAULT_RANKING, 0, np.random.default_rng(0)) == []


def test_smoke_study_on_tiny_artifacts(tiny, capsys):
    runs = rv.run_study(tiny, tiny_cfg(epochs_stage1=1), [0, 2], [42, 43], draws=1)
    assert {(r["selection"], r["k"]) for r in runs} == {("none", 0), *((s, 2) for s in rv.SELECTIONS)}
    assert len(runs) == 2 * (1 + len(rv.SELECTIONS)) and all(np.isfinite(r["iou"]) for r in runs)
    rows = rv.summarize(runs, [0, 2], [42, 43])
    by = {(r["selection"], r["k"]): r for r in rows}
    assert "gain" in by[("random", 2)] and "vs_random" in by[(rv.DEFAULT_RANKING, 2)]
    assert "vs_random" not in by[("random", 2)]
    rv.print_table(rows)
    assert "by construction" in capsys.readouterr().out


def test_a_subset_of_selections_trains_only_those_and_reports_each_finished_run(tiny):
    seen = []
    runs = rv.run_study(tiny, tiny_cfg(epochs_stage1=1), [0, 2], [42], draws=1, selections=(rv.DEFAULT_RANKING,),
                        done=lambda done: seen.append(len(done)))
    assert [(r["selection"], r["k"]) for r in runs] == [("none", 0), (rv.DEFAULT_RANKING, 2)]
    assert seen == [1, 2]  # a killed study keeps what it finished
    (row,) = [r for r in rv.summarize(runs, [0, 2], [42], (rv.DEFAULT_RANKING,)) if r["k"] == 2]
    assert "gain" in row and "vs_random" not in row  # no random run, so no ranking-minus-random


def test_k0_can_be_scored_from_existing_plain_checkpoints(tiny, tmp_path):
    from pipeline.artifacts.weights import write_weights
    from pipeline.methods import get_method
    from pipeline.training import loop as training
    from pipeline.training.inputs import load_inputs

    cfg = tiny_cfg(epochs_stage1=1)
    data, val, _ = load_inputs(tiny, get_method("plain"), cfg)
    other = training.train(get_method("plain"), cfg, data, val, 43, checkpointer=NoCheckpointer(),
                           show_progress=False).model
    (tmp_path / "42").mkdir()  # seed 43's weights under seed 42's name: the scores must be seed 43's
    write_weights(tmp_path / "42", other.mask_path_state_dict(), other.config)
    (scored,) = rv.run_study(tiny, cfg, [0], [42], draws=1, k0_checkpoints=tmp_path)
    (trained_43,) = rv.run_study(tiny, cfg, [0], [43], draws=1)
    (trained_42,) = rv.run_study(tiny, cfg, [0], [42], draws=1)
    assert scored["ious"] == trained_43["ious"] != trained_42["ious"] and scored["seed"] == 42
