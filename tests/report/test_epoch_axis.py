"""Both training-curve figures draw a warm-started Stage-II run after its own Stage-I run's last epoch (issue 63,
item 6): each seed's, since a plateau rule stops each Stage-I run at its own epoch; from-scratch runs keep theirs."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd

from pipeline.report import build


def _log(method: str, seed: int, epochs: range, iou: float) -> pd.DataFrame:
    e = np.asarray(list(epochs))
    return pd.DataFrame({"epoch": e, "stage": 1 if method in ("plain", "gabi") else 2, "method": method, "seed": seed,
                         "val_iou": iou + 0.01 * e, "val_iou_cal": iou + 0.02 * e, "loss": 1.0 - 0.01 * e})


LOGS = pd.concat([_log("plain", 42, range(1, 6), 0.5), _log("plain", 3407, range(1, 4), 0.5),  # last 5 / 3
                  _log("geodistill", 42, range(0, 3), 0.6), _log("geodistill", 3407, range(0, 3), 0.6),
                  _log("continuation", 42, range(0, 2), 0.6),
                  _log("gabi", 42, range(1, 3), 0.4),                  # Stage II from scratch: its own epochs
                  _log("geodistill", 7, range(0, 2), 0.6)],           # no Stage-I log at seed 7: its own epochs
                 ignore_index=True)


def test_warm_started_runs_sit_after_their_seed_s_last_stage_one_epoch():
    axis = build.on_one_epoch_axis(LOGS)

    def at(method, seed):
        return axis.loc[(axis["method"] == method) & (axis["seed"] == seed), build.AXIS_EPOCH].tolist()

    assert at("plain", 42) == [1, 2, 3, 4, 5] and at("plain", 3407) == [1, 2, 3]
    assert at("geodistill", 42) == [5, 6, 7] and at("geodistill", 3407) == [3, 4, 5]
    assert at("continuation", 42) == [5, 6]
    assert at("gabi", 42) == [1, 2] and at("geodistill", 7) == [0, 1]
    assert axis["epoch"].tolist() == LOGS["epoch"].tolist()          # the runs' own epochs are kept


def test_both_training_curve_figures_draw_the_shared_axis(monkeypatch):
    drawn = {}
    line_plot = build.F.line_plot

    def recording(series, title, xlabel, ylabel, **kw):
        drawn[ylabel] = ({s["label"]: s["x"].tolist() for s in series}, xlabel)
        return line_plot(series, title, xlabel, ylabel, **kw)

    monkeypatch.setattr(build.F, "line_plot", recording)
    inp = SimpleNamespace(logs=LOGS, no_masks=False, fixed_tau=0.5, need=lambda *a: [], runs=[])
    build.training_section(inp, {})
    build.epoch_calibrated_figure(LOGS, 0.5)
    assert set(drawn) == {"val Image IoU", "val Image IoU at calibrated tau"}
    label = build.T.label
    for series, xlabel in drawn.values():
        assert xlabel == build.EPOCH_AXIS
        assert series[label("plain")] == [1, 2, 3, 4, 5]
        # seed 42 from epoch 5, seed 3407 from epoch 3, seed 7 (no Stage-I log) from 0: the mean at each place
        assert series[label("geodistill")] == [0, 1, 3, 4, 5, 6, 7]
        assert series[label("continuation")] == [5, 6] and series[label("gabi")] == [1, 2]
