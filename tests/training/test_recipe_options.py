"""Recipe options of issue 17 item 4 (train.norm, train.bn_momentum, train.precise_bn) and the recipe
study script (benchmarks/study_recipe.py).

The options default to the paper recipe: a default run builds exactly the model it built before
(same modules, config and weights), and the options enter every method's params keys so that DVC
reruns training when one changes.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from torch import nn

from tests.builders.training import load_arrays, tiny_cfg
from pipeline.training.checkpointing import NoCheckpointer


def _batchnorms(model):
    return [m for m in model.modules() if isinstance(m, nn.BatchNorm2d)]


# --------------------------------------------------------------------------------------------------
# defaults = the paper recipe, unchanged
# --------------------------------------------------------------------------------------------------
def test_defaults_are_the_paper_recipe_and_build_the_same_model():
    from pipeline.methods import get_method
    from pipeline.model import TinyUNet
    from pipeline.params import PAPER
    from pipeline.training.loop import build_model

    assert (PAPER.train.norm, PAPER.train.bn_momentum, PAPER.train.precise_bn) == ("batch", 0.1, False)
    cfg = tiny_cfg()
    model = build_model(get_method("plain"), cfg, seed=7)
    torch.manual_seed(7)
    before = TinyUNet(channels=tuple(cfg["channels"]))  # the construction before the options existed
    assert model.config == {"in_channels": 3, "channels": list(cfg["channels"])}  # checkpoint bytes unchanged
    assert list(model.state_dict()) == list(before.state_dict())
    for k, v in before.state_dict().items():
        assert torch.equal(model.state_dict()[k], v), k
    assert all(bn.momentum == 0.1 for bn in _batchnorms(model)) and len(_batchnorms(model)) == 10


def test_schema_bounds():
    from pipeline.runtime.errors import InputError
    from pipeline.profiles import load_profile

    assert load_profile("paper", ["train.norm=group"])["train"]["norm"] == "group"
    for bad in ("train.norm=layer", "train.bn_momentum=0", "train.bn_momentum=1.5", "train.precise_bn=1"):
        with pytest.raises(InputError, match=bad.split("=")[0].split(".")[1]):
            load_profile("paper", [bad])


def test_options_enter_every_methods_params_and_fingerprint():
    from pipeline.methods import METHODS, fingerprint_params, param_keys
    from pipeline.params import PAPER

    cfg = tiny_cfg()
    calibrate = PAPER.calibrate.model_dump()
    for m in METHODS.values():
        keys = param_keys(m)
        assert {"train.norm", "train.bn_momentum", "train.precise_bn"} <= set(keys), m.name
        assert fingerprint_params(m, {"train": cfg, "calibrate": calibrate}) != \
            fingerprint_params(m, {"train": {**cfg, "precise_bn": True}, "calibrate": calibrate})


# --------------------------------------------------------------------------------------------------
# the model options
# --------------------------------------------------------------------------------------------------
def test_groupnorm_model_has_no_batch_statistics_and_reloads_from_its_config():
    from pipeline.model import TinyUNet

    torch.manual_seed(0)
    m = TinyUNet(channels=(8, 16, 24), norm="group")
    assert not _batchnorms(m)
    gns = [x for x in m.modules() if isinstance(x, nn.GroupNorm)]
    assert [g.num_groups for g in gns[:2]] == [1, 1] and max(g.num_groups for g in gns) == 3  # 8 ch per group
    assert m.config["norm"] == "group"
    x = torch.rand(2, 3, 16, 16)
    m.train()
    out_train = m(x)
    m.eval()
    assert torch.allclose(out_train, m(x), atol=1e-6)  # no train/eval difference without batch statistics
    again = TinyUNet(**m.config)  # how checkpoints and export rebuild it
    again.load_state_dict(m.state_dict())
    assert torch.equal(again.eval()(x), m(x))


def test_bn_momentum_reaches_every_batchnorm():
    from pipeline.methods import get_method
    from pipeline.training.loop import build_model

    model = build_model(get_method("plain"), tiny_cfg(bn_momentum=0.01), seed=0)
    assert {bn.momentum for bn in _batchnorms(model)} == {0.01}


def test_recompute_bn_stats_is_the_average_of_batch_statistics():
    from pipeline.model import TinyUNet, recompute_bn_stats

    torch.manual_seed(0)
    m = TinyUNet(channels=(4, 8, 8))
    w_before = {k: v.clone() for k, v in m.state_dict().items() if "running" not in k}
    batches = [torch.rand(2, 3, 16, 16) * (i + 1) for i in range(3)]
    first = m.enc1[0]  # conv -> BN: the first BN's input is the conv output, independent of other BNs
    with torch.no_grad():
        feats = [first[0]((b - m.MEAN) / m.STD) for b in batches]
    want_mean = torch.stack([f.mean((0, 2, 3)) for f in feats]).mean(0)
    want_var = torch.stack([f.var((0, 2, 3), unbiased=True) for f in feats]).mean(0)
    m.eval()
    assert recompute_bn_stats(m, batches) == 3
    bn = first[1]
    assert torch.allclose(bn.running_mean, want_mean, atol=1e-5)
    assert torch.allclose(bn.running_var, want_var, rtol=1e-4)
    assert bn.momentum == 0.1 and int(bn.num_batches_tracked) == 0  # restored
    assert not m.training  # mode restored
    for k, v in w_before.items():
        if "num_batches" not in k:
            assert torch.equal(m.state_dict()[k], v), k  # weights untouched
    stats = bn.running_mean.clone()
    assert recompute_bn_stats(m, []) == 0 and torch.equal(bn.running_mean, stats)  # no batch: unchanged
    assert recompute_bn_stats(TinyUNet(channels=(4, 8, 8), norm="group"), batches) == 0


def test_precise_bn_changes_running_statistics_only(tiny):
    """Same training trajectory (weights) with and without precise BN; the selected model's BN
    statistics are the training set's average batch statistics."""
    from pipeline.training import loop as training
    from pipeline.methods import get_method
    from pipeline.model import recompute_bn_stats

    cfg = tiny_cfg(epochs_stage1=2)
    data, _ = load_arrays(tiny, "plain", cfg)
    runs = {}
    for flag in (False, True):  # no validation data: the last epoch is selected in both runs
        runs[flag] = training.train(get_method("plain"), {**cfg, "precise_bn": flag}, data, None, 42,
                                    checkpointer=NoCheckpointer(), show_progress=False).model
    a, b = runs[False].state_dict(), runs[True].state_dict()
    for k in a:
        if "running_" in k:
            continue
        assert torch.equal(a[k], b[k]), k
    assert not torch.allclose(a["enc2.0.1.running_var"], b["enc2.0.1.running_var"])
    # the precise statistics are a function of the final weights and the training images only
    x = torch.from_numpy(np.asarray(data.images)).permute(0, 3, 1, 2).float() / 255.0
    recompute_bn_stats(runs[False], [x[i:i + cfg["batch_size"]] for i in range(0, len(x), cfg["batch_size"])])
    for k, v in runs[False].state_dict().items():
        assert torch.allclose(v.float(), b[k].float(), atol=1e-5), k


def test_precise_bn_in_the_train_stage_log_differs_from_ema(tiny):
    """With validation data, precise BN changes what validation sees (the log's val_iou)."""
    from pipeline.training import loop as training
    from pipeline.methods import get_method

    cfg = tiny_cfg(epochs_stage1=1)
    data, val = load_arrays(tiny, "plain", cfg)
    logs = [training.train(get_method("plain"), {**cfg, "precise_bn": f}, data, val, 42,
                           checkpointer=NoCheckpointer(), show_progress=False).log for f in (False, True)]
    assert logs[0]["loss"].tolist() == logs[1]["loss"].tolist()
    assert logs[0]["val_iou"].tolist() != logs[1]["val_iou"].tolist()


# --------------------------------------------------------------------------------------------------
# the study script
# --------------------------------------------------------------------------------------------------
def test_study_helpers():
    from benchmarks import study_recipe as sr

    assert sr.max_adjacent_jump(np.array([0.1, 0.4, np.nan, 0.3, 0.35])) == pytest.approx(0.3)
    assert sr.max_adjacent_jump(np.array([0.5])) == 0.0
    gt = np.zeros((3, 4, 4), bool)
    gt[0, :2] = True
    gt[1, 0, 0] = True
    pred = np.zeros_like(gt)
    pred[0] = True
    np.testing.assert_allclose(sr.area_ratios(pred, gt), [2.0, 0.0])  # the empty reference is left out
    tiny_masks = np.zeros((8, 32, 32), bool)
    tiny_masks[:, 0, 0] = True  # 1 px of 1024: pi = 1023 -> clipped
    s = sr.pos_weight_stats(tiny_masks, 4, seed=0, epochs=2, max_weight=500.0)
    assert s["share_at_clip"] == 1.0 and s["median_pi"] == 500.0 and s["n_batches"] == 4
    big = np.zeros((8, 32, 32), bool)
    big[:, :16] = True
    assert sr.pos_weight_stats(big, 4, 0, 1, 500.0)["share_at_clip"] == 0.0
    rows = sr.summarize([{"variant": v, "method": "plain", "seed": 0, **{c: x for c in sr.COLUMNS},
                          "val_iou_cal_curve": [0.2, 0.2 + x, 0.3]} for v, x in (("paper", 0.4), ("fp32", 0.5))])
    assert rows[1]["d_iou_cal"] == pytest.approx(0.1) and rows[0]["d_iou_cal"] == 0.0
    assert rows[0]["max_jump_cal"] == pytest.approx(0.4) and rows[1]["d_max_jump_cal"] == pytest.approx(0.1)


def test_study_runs_end_to_end_on_tiny_artifacts(tiny, tmp_path, capsys):
    from benchmarks import study_recipe as sr

    out = tmp_path / "study.json"
    res = sr.main(["--artifacts", str(tiny), "--resolution", "32", "--epochs", "1", "--seeds", "0",
                   "--variants", "paper", "precise_bn", "--out", str(out)])
    text = capsys.readouterr().out
    assert "precise_bn" in text and "supervised_ceiling" in text
    saved = json.loads(out.read_text())
    assert len(saved["runs"]) == 4 and saved["info"]["epochs"] == 1
    assert {(r["variant"], r["method"]) for r in saved["runs"]} == {
        (v, m) for v in ("paper", "precise_bn") for m in ("plain", "supervised_ceiling")}
    for r in res["runs"]:
        assert 0.0 <= r["iou_cal"] <= 1.0 and 0.05 <= r["tau_cal"] <= 0.95 and len(r["val_iou_curve"]) == 1
        assert r["steps_run"] >= 1 and r["stopped"] is None  # a fixed length: no stopping rule ran
    # a rerun reuses the finished runs of <out>.runs.jsonl (no training: same numbers, same seconds)
    lines = (tmp_path / "study.json.runs.jsonl").read_text().splitlines()
    assert len(lines) == 5
    again = sr.main(["--artifacts", str(tiny), "--resolution", "32", "--epochs", "1", "--seeds", "0",
                     "--variants", "paper", "precise_bn", "--out", str(out)])
    assert again["runs"] == json.loads(json.dumps(res["runs"]))
    assert len((tmp_path / "study.json.runs.jsonl").read_text().splitlines()) == 5


def test_study_set_overrides_the_profile_recipe(tiny, tmp_path):
    """``--set`` reaches the training settings: batch 2 gives ceil(n / 2) batches per epoch."""
    from benchmarks import study_recipe as sr

    res = sr.main(["--artifacts", str(tiny), "--resolution", "32", "--epochs", "1", "--seeds", "0", "--variants",
                   "paper", "--methods", "plain", "--set", "train.batch_size=2", "--out", str(tmp_path / "s.json")])
    n = res["info"]["n_train"]["plain"]
    assert res["info"]["pos_weight"]["plain"]["n_batches"] == -(-n // 2)


# --------------------------------------------------------------------------------------------------
# issue 43: the weights' moving average and soft targets (recipe parts)
# --------------------------------------------------------------------------------------------------
def test_ema_final_model_is_the_moving_average_of_the_steps(tiny):
    """train.ema_decay d: e <- d e + (1 - d) w after every step; the final model holds e (BN recomputed)."""
    from pipeline.training import loop as training
    from pipeline.methods import get_method

    cfg = tiny_cfg(ema_decay=0.5, epochs_stage1=1)
    data, val = load_arrays(tiny, "plain", cfg)
    seen = []
    real = training._step

    def spy(run, b, epoch, step):
        out = real(run, b, epoch, step)
        seen.append([p.detach().clone() for p in run.model.parameters()])
        return out

    import unittest.mock as mock

    with mock.patch.object(training, "_step", spy):
        res = training.train(get_method("plain"), cfg, data, val, 3, checkpointer=NoCheckpointer(),
                             show_progress=False)
    first = training.build_model(get_method("plain"), cfg, 3)
    ema = [p.detach().clone() for p in first.parameters()]
    for w in seen:
        ema = [0.5 * e + 0.5 * x for e, x in zip(ema, w)]
    for got, want in zip(res.model.parameters(), ema):
        torch.testing.assert_close(got, want)
    assert "moving average" in res.info["selection"]
    plain = training.train(get_method("plain"), tiny_cfg(epochs_stage1=1), data, val, 3,
                           checkpointer=NoCheckpointer(), show_progress=False)
    assert not all(torch.equal(a, b) for a, b in zip(plain.model.parameters(), res.model.parameters()))


def test_the_agreement_weight_reads_the_agreement_map_in_stage_one_only(tiny):
    """train.agreement_weight: Stage I reads A (its weights come from it; the loss takes M^T = [A >= 1/2] as the
    target), a Stage-II method the voted mask, as without the part."""
    from pipeline.artifacts.store import open_artifact
    from pipeline.methods import get_method
    from pipeline.training.inputs import agreement_target

    cfg = tiny_cfg(agreement_weight=1.0)
    assert agreement_target(get_method("plain"), cfg) and not agreement_target(get_method("plain"), tiny_cfg())
    assert not agreement_target(get_method("geodistill"), cfg)
    data, _ = load_arrays(tiny, "plain", cfg)
    agreement = open_artifact(tiny / "consensus.zarr").numpy("agreement")
    rows = np.arange(len(data))
    assert np.array_equal(np.asarray(data.mask[rows]), agreement[: len(rows)])


def test_soft_targets_train_on_the_agreement_map(tiny):
    """train.soft_targets: the region target is A (eq:agreement-map), float in [0, 1], not M^T."""
    from pipeline.artifacts.store import open_artifact

    data, _ = load_arrays(tiny, "plain", tiny_cfg(soft_targets=True))
    hard, _ = load_arrays(tiny, "plain", tiny_cfg())
    agreement = open_artifact(tiny / "consensus.zarr").numpy("agreement")
    rows = np.arange(len(data))
    soft = np.asarray(data.mask[rows])
    assert soft.dtype == np.float32 and np.array_equal(soft, agreement[: len(soft)])
    assert np.array_equal(np.asarray(hard.mask[rows]), agreement[: len(soft)] >= 0.5)
    assert ((soft > 0) & (soft < 1)).any()
    # the augmentation's rescale resamples the soft target bilinearly and keeps it in [0, 1]
    from pipeline.augment import AugmentSpec, GeometryConstants, augment_batch
    from pipeline.params import AugmentParams

    spec = AugmentSpec.from_params({**AugmentParams().model_dump(), "scale_probability": 1.0})
    imgs, targets = augment_batch(np.asarray(data.images[rows]), {"mask": soft, "area": data.area},
                                  [[0, 1, int(i)] for i in rows], spec, GeometryConstants())
    assert targets["mask"].dtype == np.float32 and targets["mask"].min() >= 0 and targets["mask"].max() <= 1
    assert ((targets["mask"] > 0) & (targets["mask"] < 1)).any()
