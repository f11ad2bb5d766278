"""Issue 44, a benchmark in proportion: `geodistill distill` times a small plan (or none with
``--no-benchmark``) while the DVC benchmark stage of ``make demo`` and the other profiles keeps the full
table.  (bf16 on a CPU without native bf16 is never called: tests/deploy/test_fast_paths.py.)"""

from __future__ import annotations

import yaml
from click.testing import CliRunner

import pipeline
from pipeline.engine_table import BENCHMARK_VARIANTS
from pipeline.params import PAPER
from pipeline.profiles import DISTILL_BENCHMARK, PROFILES, load_profile
from tests.builders.lane import REPO
from tests.builders.teacher import checkpoint_folder, make_image_folder

PLAN_KEYS = ("benchmark_variants", "benchmark_warmup", "benchmark_iters", "benchmark_batches")


def test_distill_plans_a_small_benchmark_and_the_dvc_stage_keeps_the_full_table():
    small = load_profile("distill")["deploy"]
    assert {k: small[k] for k in PLAN_KEYS} == DISTILL_BENCHMARK
    assert len(small["benchmark_variants"]) <= 3 and small["benchmark_batches"] == [1]
    assert not any("bf16" in v for v in small["benchmark_variants"])
    full = PAPER.deploy
    assert full.benchmark_variants == BENCHMARK_VARIANTS and full.benchmark_warmup > small["benchmark_warmup"]
    for name in PROFILES:
        if name != "distill":  # every other profile times every variant
            assert load_profile(name)["deploy"]["benchmark_variants"] == BENCHMARK_VARIANTS, name
    # the repository's params.yaml: the DVC benchmark stage `make demo` runs
    demo = yaml.safe_load((REPO / "params.yaml").read_text())["deploy"]
    assert demo["benchmark_variants"] == BENCHMARK_VARIANTS and demo["benchmark_batches"] != [1]


def _project(tmp_path, *flags):
    from pipeline.cli.main import main

    images = tmp_path / "data" / "images"
    if not images.is_dir():
        make_image_folder(tmp_path / "data", n=3, masks=False)
    sam3 = checkpoint_folder(tmp_path / "sam3")  # the project is written, not run
    out = tmp_path / "run"
    r = CliRunner().invoke(main, ["distill", str(images), "--out", str(out), "--checkpoint", str(sam3), "--no-run",
                                  *flags])
    assert r.exit_code == 0, r.output
    return images, sam3, out, yaml.safe_load((out / "dvc.yaml").read_text())["stages"]


def test_no_benchmark_leaves_the_stage_out_and_a_rerun_without_it_puts_it_back(tmp_path):
    images, sam3, out, stages = _project(tmp_path, "--no-benchmark")
    assert "benchmark" not in stages and "export" in stages and "report" in stages
    assert not any("efficiency" in d for d in stages["report"]["deps"])  # the report does without it
    _, _, _, stages = _project(tmp_path)  # the same command without the flag
    assert "benchmark" in stages and any("efficiency" in d for d in stages["report"]["deps"])
    params = yaml.safe_load((out / "params.yaml").read_text())["deploy"]
    assert {k: params[k] for k in PLAN_KEYS} == DISTILL_BENCHMARK  # distill's small plan
    pipeline.distill(images, out=out, checkpoint=sam3, run=False, benchmark=False)  # the keyword, in Python
    assert "benchmark" not in yaml.safe_load((out / "dvc.yaml").read_text())["stages"]


def test_bench_distill_times_both_cases_round_robin_and_prints_the_ratio(capsys):
    """Smoke test of benchmarks/bench_distill.py with a fake runner whose cost is declared (no run,
    no timing): both cases every round in alternating order, fresh folders, the ratio against the target."""
    from benchmarks import bench_distill

    seen = []

    def fake(argv):
        one = any(a.startswith("deploy.benchmark_variants=") for a in argv)
        seen.append(("one" if one else "default", argv[argv.index("--out") + 1]))
        return 10.0 if one else 12.0

    times = bench_distill.main(["imgs", "--checkpoint", "sam3", "--reps", "3", "--set", "train.epochs_stage1=1"],
                               run=fake)
    assert [s[0] for s in seen] == ["one", "default", "default", "one", "one", "default"]
    assert len({s[1] for s in seen}) == 6  # every run computes the whole DAG in a fresh project
    assert times == {"one variant": [10.0] * 3, "default": [12.0] * 3}
    out = capsys.readouterr().out
    assert "default / one variant: 1.20x (medians), 1.20x (minima); target <= 1.5x: met" in out
