#!/bin/bash
# The prepared GPU script (issue 57 item 6, issue 58 item 4).  It returns ONLY metrics, logs and meta.json under
# $OUT (< 5 MB: $OUT/results.tar.gz, meta.json, the headline JSONs, run.log) and stops within DEADLINE seconds:
# each section runs under a guard (reports/gpu/collect.py run: its own process group, SIGTERM then SIGKILL at its
# budget), COLLECT_S seconds stay for the collection, and whatever finished is collected.  Never artifacts
# (*.zarr, weights, images): the 2026-11-27 run lost every score because its archive of them was 114 MB.
#
# Prepare .gpu/ here first: reports/gpu/prepare.sh (wheels .gpu/whl, code .gpu/src, runner .gpu/dagrun.py and
# .gpu/stub, optionally the DAG project .gpu/proj).  Then, with the device tool (timeout_s 600, carry [".gpu"]):
#
#   WINNER=bootstrap DEADLINE=560 bash reports/gpu/run.sh
#
# Sections (SECTIONS, in order; default "teacher past_labels"):
#   teacher      issue 58 item 4: the real-size SAM 3 (random weights), bf16, compiled and eager, batches
#                TEACHER_BATCHES: peak memory and ms per image (benchmarks/bench_teacher.py --batch-sweep; its logic
#                tested on a CPU in tests/benchmarks/test_bench_teacher_roofline.py) -> teacher_gpu.json
#   past_labels  issue 57 item 6: Stage I at RESOLUTION (384) on the reduced profile's data (the paper's sizes,
#                270 / 60 / 3x60, as the plateau-384 run), recipe RECIPE (progressive), seed SEED: Plain, the
#                ceiling and WINNER, a variant of benchmarks.past_labels (bootstrap, ignore_band, soft,
#                self_training; empty = Plain and the ceiling only) -> past_labels.json (+ .runs.jsonl, one line per
#                finished run, kept when the deadline cuts the rest)
#   dag          dagrun.py on the project copy PROJ (.gpu/proj), deadline = its budget - 15 s -> its logs,
#                timings.json, reports/**/*.md|json|csv, dvclive metrics, artifacts/<table>.parquet as JSON
#
# Settings (environment): OUT (required: the folder that comes back), DEADLINE (540 s, the whole script),
# COLLECT_S (20), MIN_SECTION_S (20: a section with less time left is skipped), WORK (/tmp/gd-gpu), GPU_DIR (<repo>/.gpu), PYTHON (python3), DEVICE (cuda); TEACHER_S (200),
# TEACHER_BATCHES ("1 2 4 8 16 32"), TEACHER_SIZE (real), TEACHER_REPEATS (5), TEACHER_PATHS ("compiled eager");
# WINNER, RESOLUTION (384), RECIPE (progressive), SEED (42), PL_PROFILE (reduced), PL_JOBS (3), PL_THREADS (4),
# PL_S (the time left), PL_ARGS (more past_labels arguments, e.g. "--epochs 60 --set train.lr=1e-3");
# PROJ, DAGRUN (<GPU_DIR>/dagrun.py, else ../shared/tools/gpu/dagrun.py), DAG_S (the time left), GD_PAR (8).
#
# Record every figure with the date and the card that meta.json gives (../shared/tools/gpu/README.md).
set -u
T0=$(date +%s)
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
HERE=$ROOT/reports/gpu
: "${OUT:?OUT: the folder whose files come back}"
GPU_DIR=${GPU_DIR:-$ROOT/.gpu}
WORK=${WORK:-/tmp/gd-gpu}
PY=${PYTHON:-python3}
DEADLINE=${DEADLINE:-540}
COLLECT_S=${COLLECT_S:-20}
SECTIONS=${SECTIONS:-teacher past_labels}
DEVICE=${DEVICE:-cuda}
END=$((T0 + DEADLINE))
SRC=$ROOT
[ -d "$GPU_DIR/src" ] && SRC=$GPU_DIR/src
PROJ=${PROJ:-$GPU_DIR/proj}
DAGRUN=${DAGRUN:-}
if [ -z "$DAGRUN" ]; then
  DAGRUN=$GPU_DIR/dagrun.py
  [ -f "$DAGRUN" ] || DAGRUN=$ROOT/../shared/tools/gpu/dagrun.py
fi
mkdir -p "$OUT" "$WORK/logs"
exec > >(tee -a "$WORK/run.log") 2>&1

C="$PY $HERE/collect.py"
GUARD="$C run --work $WORK --end $END --reserve $COLLECT_S --min-budget ${MIN_SECTION_S:-20}"
settings=$(printf '{"WINNER":"%s","RESOLUTION":"%s","RECIPE":"%s","SEED":"%s","PL_PROFILE":"%s","PL_ARGS":"%s","TEACHER_BATCHES":"%s","TEACHER_SIZE":"%s","DEVICE":"%s","PROJ":"%s","GD_PAR":"%s"}' \
  "${WINNER:-bootstrap}" "${RESOLUTION:-384}" "${RECIPE:-progressive}" "${SEED:-42}" "${PL_PROFILE:-reduced}" "${PL_ARGS:-}" \
  "${TEACHER_BATCHES:-1 2 4 8 16 32}" "${TEACHER_SIZE:-real}" "$DEVICE" "$PROJ" "${GD_PAR:-8}")
$C begin --out "$OUT" --work "$WORK" --src "$SRC" --python "$PY" --deadline "$DEADLINE" --reserve "$COLLECT_S" \
  --started "$T0" --sections "$SECTIONS" --settings "$settings"

# the packages the device's image lacks (prepare.sh), into a folder of their own
if ls "$GPU_DIR"/whl/*.whl > /dev/null 2>&1; then
  $GUARD --name install --budget 120 -- $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
    --upgrade --target /tmp/site "$GPU_DIR"/whl/*.whl
  export PYTHONPATH=/tmp/site:${PYTHONPATH:-}
fi
export PYTHONPATH=$GPU_DIR/stub:$SRC:${PYTHONPATH:-} PYTHONUNBUFFERED=1 SOURCE_DATE_EPOCH=315532800

# Plain and the ceiling, then each WINNER variant once (a lever not in benchmarks.past_labels.VARIANTS goes there)
VARIANTS="plain ceiling"
for w in ${WINNER:-bootstrap}; do case " $VARIANTS " in *" $w "*) ;; *) VARIANTS="$VARIANTS $w" ;; esac; done

for section in $SECTIONS; do
  case $section in
    teacher)
      # shellcheck disable=SC2086
      $GUARD --name teacher --budget "${TEACHER_S:-200}" --cwd "$SRC" -- $PY -m benchmarks.bench_teacher \
        --batch-sweep "$(echo ${TEACHER_BATCHES:-1 2 4 8 16 32} | tr ' ' ',')" --device "$DEVICE" \
        --size "${TEACHER_SIZE:-real}" --dtype bf16 --paths "$(echo ${TEACHER_PATHS:-compiled eager} | tr ' ' ',')" \
        --repeats "${TEACHER_REPEATS:-5}" --resolution 384 --deadline '{deadline}' --json "$WORK/teacher_gpu.json" ;;
    past_labels)
      # shellcheck disable=SC2086
      $GUARD --name past_labels ${PL_S:+--budget "$PL_S"} --cwd "$SRC" -- $PY -m benchmarks.past_labels \
        --profile "${PL_PROFILE:-reduced}" --resolution "${RESOLUTION:-384}" --set "train.recipe=${RECIPE:-progressive}" \
        --seeds "${SEED:-42}" --variants $VARIANTS --device "$DEVICE" --jobs "${PL_JOBS:-3}" \
        --threads "${PL_THREADS:-4}" --workdir "$WORK/past_labels" --out "$WORK/past_labels.json" ${PL_ARGS:-} ;;
    dag)
      GD_PAR=${GD_PAR:-8} $GUARD --name dag ${DAG_S:+--budget "$DAG_S"} --margin 15 -- $PY "$DAGRUN" "$PROJ" '{deadline}' ;;
    *)
      echo "run.sh: SECTIONS: unknown section '$section' (expected teacher, past_labels, dag)" ;;
  esac
done

$C finish --out "$OUT" --work "$WORK" --started "$T0" $(case " $SECTIONS " in *" dag "*) echo --proj "$PROJ";; esac)
ls -la "$OUT"
