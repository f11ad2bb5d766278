"""Smoke test of the label-noise screening benchmark (benchmarks/past_labels.py) on the tiny artifacts."""

from __future__ import annotations

import json
import types

import numpy as np
import pytest

from benchmarks import past_labels
from pipeline.report.dvc_results import distillation_efficiency


def test_every_variant_trains_scores_and_resumes(tiny, tmp_path, capsys, monkeypatch):
    out = tmp_path / "p.json"
    argv = ["--artifacts", str(tiny), "--resolution", "32", "--epochs", "1", "--seeds", "1", "--threads", "1",
            "--variants", *past_labels.VARIANTS, "--out", str(out)]
    doc = past_labels.main(argv)
    runs = {r["variant"]: r for r in doc["runs"]}
    assert set(runs) == set(past_labels.VARIANTS)
    assert all(0 <= r["iou_cal"] <= 1 and set(r["groups"]) == set(r["vote_groups"]) for r in runs.values())
    assert runs["ceiling"]["trained"] == "supervised_ceiling" and runs["plain"]["trained"] == "plain"
    assert runs["ceiling_expand"]["trained"] == "supervised_ceiling" and runs["expand"]["trained"] == "plain"
    assert runs["bf16"]["steps_run"] == runs["plain"]["steps_run"]  # equal steps: only the precision differs
    assert runs["photometric"]["trained"] == "plain" and runs["ceiling_photometric"]["trained"] == "supervised_ceiling"
    # self-training relabels every training image twice (flip TTA) and counts plain's training in its cost
    st = runs["self_training"]
    assert st["relabel_passes"] == past_labels.TTA_PASSES * st["n_train"] and st["n_train"] == runs["plain"]["n_train"]
    assert runs["plain"]["relabel_passes"] == 0
    # each run names the CPU it trained on: runs of two hosts are paired only knowing it
    assert all(r["host"]["cpu"] and "numpy_simd" in r["host"] and r["host"]["vendor"] is not None
               for r in runs.values())
    rows = {r["variant"]: r for r in doc["summary"]}
    assert rows["self_training"]["cost"] == pytest.approx(
        st["images_seen"] + runs["plain"]["images_seen"] + past_labels.RELABEL_WEIGHT * st["relabel_passes"])
    assert rows["ceiling"]["of_ceiling"] == {g: 1.0 for g in rows["ceiling"]["groups"]}
    assert json.loads(out.read_text())["summary"] == doc["summary"]
    capsys.readouterr()
    again = past_labels.main(argv)  # every run is in the runs file: nothing trains again
    assert again["runs"] == doc["runs"] and "done" not in capsys.readouterr().out
    both = past_labels.main(["--resolution", "32", "--combine", str(out), str(out) + ".runs.jsonl",
                             "--out", str(tmp_path / "both.json"), "--noise-floor", str(tmp_path / "none.json")])
    assert both["runs"] == doc["runs"] and both["info"]["noise_floor"] == {}
    assert {g["variant"] for g in both["gains"]} == set(past_labels.VARIANTS) - {"plain", "ceiling"}
    # a variant on the reference masks is compared with the ceiling, every other with Plain
    on_reference = {v for v, (_, kind, _) in past_labels.VARIANTS.items() if kind == "reference"} - {"ceiling"}
    assert on_reference == {"ceiling_expand", "ceiling_photometric"}
    assert {g["control"] for g in both["gains"] if g["variant"] in on_reference} == {"ceiling"}
    assert {g["control"] for g in both["gains"] if g["variant"] not in on_reference} == {"plain"}
    # one seed: no verdict speaks of support (a one-spacecraft group has no interval: not estimated)
    assert {g["verdict"] for g in both["gains"]} <= {"one seed", "not estimated"}
    assert "| bootstrap |" in capsys.readouterr().out
    # the fit of the saved plain run on its own training images, against the vote's fit there
    assert len(runs["plain"]["train_ious"]) == runs["plain"]["n_train"]
    fit = past_labels.main(["--artifacts", str(tiny), "--resolution", "32", "--seeds", "1", "--threads", "1",
                            "--fit-of-saved", "--out", str(tmp_path / "fit.json")])
    assert fit["images"] == runs["plain"]["n_train"] and fit["verdict"] == "one seed"
    assert fit["host"]["flags"] == runs["plain"]["host"]["flags"]
    assert fit["plain"]["1"] == pytest.approx(sum(runs["plain"]["train_ious"]) / fit["images"])
    assert fit["plain_minus_vote"] == pytest.approx(fit["plain"]["1"] - fit["vote"])
    assert fit["runs"]["1"]["image_ious"] == runs["plain"]["image_ious"]  # the test images too, per image
    # the threshold's transfer (a diagnosis): the oracle tau's IoU is the curve's best, never below the calibrated
    # tau's when that tau is on the diagnosis grid
    transfer = past_labels.tau_transfer(fit)
    for g, v in transfer.items():
        curve = fit["runs"]["1"]["test_tau_curve"][g]
        assert len(curve) == len(past_labels.TAU_DIAGNOSIS) and v["oracle"] == max(curve)
        assert v["oracle_tau"] == past_labels.TAU_DIAGNOSIS[curve.index(max(curve))]
        assert v["calibrated"] == fit["runs"]["1"]["groups"][g]
        if round(fit["runs"]["1"]["tau_cal"], 2) in past_labels.TAU_DIAGNOSIS:
            assert v["oracle"] >= v["calibrated"] - 1e-9
    # a threshold per image (a departure, screened beside the single tau): one row per group and one pooled, each
    # pairing the same run's test images under the two rules
    run = fit["runs"]["1"]
    assert set(run["relative_rule"]) == {"a", "b", "lo", "span", "iou"}
    assert len(run["image_ious_relative"]) == len(run["image_ious"])
    rel = {r["images"]: r for r in fit["relative_tau"]["gains"]}
    assert set(rel) == {*run["groups"], past_labels.ALL}
    assert rel[past_labels.ALL]["base"] == pytest.approx(np.mean(run["image_ious"]))
    assert rel[past_labels.ALL]["other"] == pytest.approx(np.mean(run["image_ious_relative"]))
    for g in run["groups"]:
        assert rel[g]["base"] == pytest.approx(run["groups"][g])
        assert rel[g]["other_of_vote"] == pytest.approx(rel[g]["other"] / run["vote_groups"][g])
    assert "a threshold per image" in capsys.readouterr().out
    # the test images by the benchmark's degradation: every scored image in one case, the means re-weighted
    hard_argv = ["--artifacts", str(tiny), "--resolution", "32", "--by-hard-case", str(tmp_path / "fit.json"),
                 "--out", str(tmp_path / "hard.json")]
    plain_doc = past_labels.main(hard_argv)
    assert plain_doc["groups"] == {} and plain_doc["vote"] == {}  # no hard_case in the manifest: not the synthetic benchmark
    real = past_labels.scored_test_rows

    def with_cases(artifacts):
        manifest, test = real(artifacts)
        df = manifest.df.assign(hard_case=["glare" if i % 2 else "none" for i in range(len(manifest.df))])
        return types.SimpleNamespace(df=df), test

    monkeypatch.setattr(past_labels, "scored_test_rows", with_cases)
    hard_doc = past_labels.main(hard_argv)
    hard = hard_doc["groups"]
    # the vote against the reference per degradation, on the training and the scored test images
    _, test_rows = with_cases(tiny)
    assert sum(v["images"] for v in hard_doc["vote"]["test"].values()) == len(test_rows)
    assert sum(v["images"] for v in hard_doc["vote"]["train"].values()) == runs["plain"]["n_train"]
    pooled = sum(v["images"] * v["vote"] for v in hard_doc["vote"]["test"].values()) / len(test_rows)
    assert pooled == pytest.approx(float(np.mean(past_labels.image_ious(
        past_labels.read_rows(past_labels.open_artifact(past_labels.catalog.path("consensus", tiny), "consensus"),
                              "voted", test_rows).astype(bool),
        past_labels.read_rows(past_labels.open_artifact(past_labels.catalog.path("reference", tiny), "reference"),
                              "mask", test_rows).astype(bool)))))
    assert all(v["too_many_px"] >= 0 and v["missed_px"] >= 0 for by in hard_doc["vote"].values() for v in by.values())
    # a variant's runs in a runs document (no region counts kept there)
    assert runs["expand"]["image_ious"] != runs["plain"]["image_ious"]  # so the variant read is told apart
    by_variant = past_labels.main(["--artifacts", str(tiny), "--resolution", "32", "--by-hard-case", str(out),
                                   "--saved-variant", "expand", "--out", str(tmp_path / "hard-e.json")])
    for g, by in by_variant["groups"].items():
        n = sum(v["images"] for v in by.values())
        assert sum(v["images"] * v["student"] for v in by.values()) / n == pytest.approx(runs["expand"]["groups"][g])
        assert all(v["own_background_px"] is None for v in by.values())
    monkeypatch.undo()
    assert set(hard) == set(fit["runs"]["1"]["groups"]) and all(set(by) == {"glare", "none"} for by in hard.values())
    for g, by in hard.items():
        n = sum(v["images"] for v in by.values())
        assert sum(v["images"] * v["student"] for v in by.values()) / n == pytest.approx(fit["runs"]["1"]["groups"][g])
        assert sum(v["images"] * v["vote"] for v in by.values()) / n == pytest.approx(fit["runs"]["1"]["vote_groups"][g])
    assert "| degradation |" in capsys.readouterr().out
    # the saved Plain run warm-starts each Stage-II method once; the refined model is saved and scored instead
    for method in past_labels.REFINE:
        argv_r = ["--artifacts", str(tiny), "--resolution", "32", "--seeds", "1", "--threads", "1", "--fit-of-saved",
                  "--set", "train.epochs_stage2=1", "--refine", method, "--out", str(tmp_path / f"{method}.json")]
        ref = past_labels.main(argv_r)
        path = tiny.parent / f"{method}-s1.pt"
        assert ref["method"] == method and path.is_file() and ref["runs"]["1"]["image_ious"] != fit["runs"]["1"]["image_ious"]
        stamp = path.stat().st_mtime_ns
        assert past_labels.main(argv_r)["runs"] == ref["runs"] and path.stat().st_mtime_ns == stamp  # not retrained
    assert fit["method"] == "plain" and fit["variant"] == "plain"
    # another annotation-free variant's saved run, scored as Plain's is
    other = past_labels.main(["--artifacts", str(tiny), "--resolution", "32", "--seeds", "1", "--threads", "1",
                              "--fit-of-saved", "--saved-variant", "photometric", "--out", str(tmp_path / "fp.json")])
    assert other["variant"] == "photometric" and other["runs"]["1"]["image_ious"] == runs["photometric"]["image_ious"]
    # the ceiling's saved run (NOT annotation-free) scored the same way: with Plain's at the same steps, the label cost
    ceil = past_labels.main(["--artifacts", str(tiny), "--resolution", "32", "--seeds", "1", "--threads", "1",
                             "--fit-of-saved", "--saved-variant", "ceiling", "--out", str(tmp_path / "fc.json")])
    assert ceil["method"] == "supervised_ceiling" and ceil["runs"]["1"]["image_ious"] == runs["ceiling"]["image_ious"]
    assert ceil["runs"]["1"]["train_ious"] == runs["ceiling"]["train_ious"]
    cost = {r["images"]: r for r in past_labels.compare_fits(ceil, fit, tiny)["gains"]}
    assert cost[past_labels.ALL]["other_of_base"] == pytest.approx(
        np.mean(runs["plain"]["image_ious"]) / np.mean(runs["ceiling"]["image_ious"]))
    with pytest.raises(SystemExit, match="Stage II warm-starts from Plain"):
        past_labels.main(["--artifacts", str(tiny), "--resolution", "32", "--seeds", "1", "--threads", "1",
                          "--fit-of-saved", "--saved-variant", "ceiling", "--refine", past_labels.REFINE[0],
                          "--out", str(tmp_path / "fr.json")])
    # two fit documents paired by seed and image (say 1x and 2x the steps): a saved run in its own folder, lifted
    moved = tmp_path / "saved"  # another step budget's run, saved in its own folder, leaves the first in place
    before = (tiny.parent / "plain-s1.pt").read_bytes()
    past_labels.main(["--artifacts", str(tiny), "--resolution", "32", "--epochs", "2", "--seeds", "1", "--threads",
                      "1", "--variants", "plain", "--saved-dir", str(moved), "--out", str(tmp_path / "x2.json")])
    assert (tiny.parent / "plain-s1.pt").read_bytes() == before and (moved / "plain-s1.pt").is_file()
    (moved / "plain-s1.pt").write_bytes(before)
    fit2 = past_labels.main(["--artifacts", str(tiny), "--resolution", "32", "--seeds", "1", "--threads", "1",
                             "--fit-of-saved", "--saved-dir", str(moved), "--out", str(tmp_path / "fit2.json")])
    assert fit2["runs"] == fit["runs"] and fit2["saved"] == str(moved)
    fit2["runs"]["1"]["train_ious"] = [v + 0.1 for v in fit2["runs"]["1"]["train_ious"]]
    (tmp_path / "fit2.json").write_text(json.dumps(fit2))
    cmp = past_labels.main(["--artifacts", str(tiny), "--resolution", "32", "--compare-fits",
                            str(tmp_path / "fit.json"), str(tmp_path / "fit2.json"), "--out", str(tmp_path / "c.json")])
    rows = {r["images"]: r for r in cmp["gains"]}
    assert rows["train"]["gain"] == pytest.approx(0.1) and rows[past_labels.ALL]["gain"] == 0
    assert set(rows) == {"train", past_labels.ALL, *fit["runs"]["1"]["groups"]} and cmp["seeds"] == [1]
    assert cmp["base_of_vote"] == cmp["other_of_vote"] and "| train | 1 |" in capsys.readouterr().out
    # where each side loses to the vote, per group and region: the same saved model on both sides
    assert cmp["regions"]["base"] == cmp["regions"]["other"] and set(cmp["regions"]["base"]) == set(
        fit["runs"]["1"]["groups"])
    assert rows["train"]["noise_floor"] is None  # no floor recorded for this run's key: the interval decides
    floors = {g: 0.01 * (i + 1) for i, g in enumerate(fit["runs"]["1"]["groups"])}
    held = {r["images"]: r["noise_floor"] for r in past_labels.compare_fits(fit, fit2, tiny, floors)["gains"]}
    assert held == {**floors, "train": max(floors.values()), past_labels.ALL: max(floors.values())}
    # the moonshot's readout over three seeds: each group's share of the vote with the report's interval
    three = {**fit, "runs": {str(s): {**fit["runs"]["1"], "groups": {g: v * f for g, v in
                                                                      fit["runs"]["1"]["groups"].items()}}
                             for s, f in ((1, 0.9), (2, 1.0), (3, 1.2))}}
    moon = past_labels.compare_fits(three, three, tiny)
    assert moon["seeds"] == [1, 2, 3]
    for g, v in fit["runs"]["1"]["groups"].items():
        vote = fit["runs"]["1"]["vote_groups"][g]
        want = distillation_efficiency(v * 31 / 30, float(np.std([0.9 * v, v, 1.2 * v], ddof=1)), 3, vote)
        assert moon["other_of_vote"][g] == pytest.approx(want[0])
        assert moon["of_vote_interval"]["other"][g] == pytest.approx(list(want[1:]))
        assert f"{want[0]:.2f} [{want[1]:.2f}, {want[2]:.2f}]" in past_labels.fits_table(moon)


def test_a_saved_run_is_scored_instead_of_trained(tiny, tmp_path):
    import shutil

    first = past_labels.main(["--artifacts", str(tiny), "--resolution", "32", "--epochs", "1", "--seeds", "1",
                              "--threads", "1", "--variants", "plain", "--out", str(tmp_path / "a.json")])
    run = tmp_path / "plain-s1"
    run.mkdir()
    shutil.copy(tiny.parent / "plain-s1.pt", run / "final.pt")
    (run / "done.json").write_text(json.dumps({"method": "plain", "seed": 1, "commit": "abc", "steps_run": 2,
                                               "stopped": None, "val_iou_cal": [None, 0.5]}))
    doc = past_labels.main(["--artifacts", str(tiny), "--resolution", "32", "--epochs", "1", "--seeds", "1",
                            "--threads", "1", "--variants", "plain", "--import-run", "plain", str(run),
                            "--out", str(tmp_path / "b.json")])
    (got,), (trained,) = doc["runs"], first["runs"]
    assert got["iou_cal"] == trained["iou_cal"] and got["steps_run"] == 2 and "commit abc" in got["source"]
    with pytest.raises(ValueError, match="not supervised_ceiling"):
        past_labels.main(["--artifacts", str(tiny), "--resolution", "32", "--seeds", "1", "--threads", "1",
                          "--variants", "ceiling", "--import-run", "ceiling", str(run),
                          "--out", str(tmp_path / "c.json")])


def test_a_saved_model_is_written_whole_or_not_at_all(tmp_path, monkeypatch):
    import torch

    model, path = torch.nn.Linear(3, 2), tmp_path / "plain-s1.pt"
    past_labels.save_model(model, path)
    assert torch.load(path, weights_only=True).keys() == model.state_dict().keys()

    def killed(obj, f):  # the process dies part-way through the write
        open(f, "wb").write(b"torn")
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", killed)
    with pytest.raises(KeyboardInterrupt):
        past_labels.save_model(model, tmp_path / "plain-s2.pt")
    assert not (tmp_path / "plain-s2.pt").exists()  # a rerun trains it again instead of reading a torn file
    with pytest.raises(KeyboardInterrupt):
        past_labels.save_model(model, path)
    assert torch.load(path, weights_only=True).keys() == model.state_dict().keys()  # the earlier one is intact


def test_a_variant_merges_its_sub_section_into_the_base_recipe():
    base = {"lr_stage1": 5e-4, "augmentation": {"hflip": 0.5, "flare_probability": 0.0}}
    cfg = past_labels.overlay(base, past_labels.VARIANTS["photometric"][0])
    assert cfg["augmentation"] == {"hflip": 0.5, **past_labels.PHOTOMETRIC} and cfg["lr_stage1"] == 5e-4
    assert base["augmentation"]["flare_probability"] == 0.0  # the base is not changed
    assert past_labels.overlay(base, {"lr_stage1": 1e-3})["augmentation"] is base["augmentation"]


def test_gains_pair_seeds_and_images_and_clear_the_noise_floor():
    import numpy as np

    rng = np.random.default_rng(0)
    base = {s: rng.uniform(0.3, 0.7, 12) for s in (1, 2, 3)}
    runs = [{"variant": "plain", "seed": s, "image_ious": list(v)} for s, v in base.items()]
    runs += [{"variant": "bootstrap", "seed": s, "image_ious": list(v + 0.05 + rng.normal(0, 0.005, 12))}
             for s, v in base.items()]
    runs += [{"variant": "soft", "seed": 1, "image_ious": list(base[1])}]
    craft = np.repeat(["a", "b", "c", "d"], 3)
    groups = np.array(["G"] * 12)
    got = past_labels.gains(runs, craft, groups, {"G": 0.01})
    assert [r["group"] for r in got if r["variant"] == "bootstrap"] == ["G", past_labels.ALL]  # one group = all
    rows = {r["variant"]: r for r in got if r["group"] == "G"}
    assert rows["bootstrap"]["seeds"] == [1, 2, 3] and rows["bootstrap"]["gain"] == pytest.approx(0.05, abs=0.005)
    assert rows["bootstrap"]["low"] > 0.01 and rows["bootstrap"]["verdict"] == "gain supported"
    assert rows["soft"]["gain"] == 0 and rows["soft"]["verdict"] == "one seed"  # one seed holds no training noise
    rows = {r["variant"]: r for r in past_labels.gains(runs, craft, groups, {"G": 0.06}) if r["group"] == "G"}
    assert rows["bootstrap"]["verdict"] == "no difference detected"  # its bound does not clear the floor


def test_the_pooled_row_takes_every_image_and_the_largest_floor():
    import numpy as np

    rng = np.random.default_rng(1)
    base = {s: rng.uniform(0.3, 0.7, 12) for s in (1, 2, 3)}
    lift = np.r_[np.full(6, 0.02), np.full(6, 0.06)]            # group A gains 0.02, group B 0.06
    runs = [{"variant": "plain", "seed": s, "image_ious": list(v)} for s, v in base.items()]
    runs += [{"variant": "bootstrap", "seed": s, "image_ious": list(v + lift)} for s, v in base.items()]
    groups = np.repeat(["A", "B"], 6)
    rows = {r["group"]: r for r in past_labels.gains(runs, np.repeat(list("abcdef"), 2), groups, {"A": 0.01, "B": 0.03})}
    assert set(rows) == {"A", "B", past_labels.ALL}
    assert rows[past_labels.ALL]["gain"] == pytest.approx(0.04) and rows[past_labels.ALL]["noise_floor"] == 0.03


def test_region_deficit_counts_own_errors_less_corrections_per_group_and_seed():
    from benchmarks.memorisation import COUNTS, REGIONS

    def counts(own_boundary, copied_blob):  # 3 images: [image, region, count]
        c = np.zeros((3, len(REGIONS), len(COUNTS)), int)
        c[:, REGIONS.index("boundary"), COUNTS.index("own_wrong")] = own_boundary
        c[:, REGIONS.index("fp_blob"), COUNTS.index("vote_wrong")] = 10
        c[:, REGIONS.index("fp_blob"), COUNTS.index("copied")] = copied_blob
        return c.tolist()

    doc = {"runs": {"1": {"test_region_counts": counts([4, 6, 1], [10, 10, 2])},
                    "2": {"test_region_counts": counts([6, 8, 3], [10, 10, 6])}}}
    out = past_labels.region_deficit(doc, np.array(["a", "a", "b"]), ["1", "2"])
    assert out["a"]["boundary"] == {"own": 6.0, "corrected": 0.0, "net": 6.0}  # (4 + 6 + 6 + 8) / 4
    # group b: 10 of the vote's wrong blob pixels, 2 then 6 copied: 8 then 4 corrected
    assert out["b"]["fp_blob"] == {"own": 0.0, "corrected": 6.0, "net": -6.0}
    assert out["b"]["boundary"]["net"] == 2.0 and out["a"]["thin"]["net"] == 0.0


def test_a_killed_run_resumes_after_its_last_epoch_with_the_same_weights(tiny, tmp_path, monkeypatch, capsys):
    """A study of hours survives its process: the run restarts from its per-epoch state, not from epoch 1, and
    ends with the weights of a run never stopped; the state goes once the run is saved."""
    argv = ["--artifacts", str(tiny), "--resolution", "32", "--epochs", "3", "--seeds", "1", "--threads", "1",
            "--variants", "plain"]
    whole = past_labels.main(argv + ["--out", str(tmp_path / "whole.json"), "--saved-dir", str(tmp_path / "w")])
    real = past_labels.training.train

    class Killed(Exception):
        pass

    def killed_after_epoch_two(*a, callback=None, **kw):
        def cb(epoch, row):
            callback(epoch, row)
            if epoch == 2:
                raise Killed

        return real(*a, callback=cb, **kw)

    monkeypatch.setattr(past_labels.training, "train", killed_after_epoch_two)
    with pytest.raises(Killed):
        past_labels.main(argv + ["--out", str(tmp_path / "cut.json"), "--saved-dir", str(tmp_path / "c")])
    job = {"saved": str(tmp_path / "c"), "variant": "plain", "seed": 1}
    assert (past_labels.resume_dir(job) / "state.pt").exists()
    trained = []

    def counted(*a, callback=None, **kw):
        return real(*a, callback=lambda e, row: (trained.append(e), callback(e, row)), **kw)

    monkeypatch.setattr(past_labels.training, "train", counted)
    capsys.readouterr()
    cut = past_labels.main(argv + ["--out", str(tmp_path / "cut.json"), "--saved-dir", str(tmp_path / "c")])
    assert "resuming from" in capsys.readouterr().out and trained == [3]  # only the epoch still to train
    (a,), (b,) = whole["runs"], cut["runs"]
    assert b["steps_run"] == a["steps_run"] and b["image_ious"] == a["image_ious"]
    assert (tmp_path / "w" / "plain-s1.pt").read_bytes() == (tmp_path / "c" / "plain-s1.pt").read_bytes()
    assert not past_labels.resume_dir(job).exists()
