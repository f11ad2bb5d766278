#!/bin/bash
# Prepare .gpu/ for reports/gpu/run.sh, here (a machine with the package index), in the checkout the device tool
# sends (its repo root), then name .gpu in the run's carry:
#
#   reports/gpu/prepare.sh              # wheels, code, runner; no DAG project
#   reports/gpu/prepare.sh paper        # also .gpu/proj: params.yaml by `geodistill profile paper`, dvc.yaml by
#                                       # `geodistill dag`, for SECTIONS=dag
#
# .gpu/whl   the packages the device's image lacks, as Python 3.12 manylinux wheels (13 MB; the list and the reason
#            in ../shared/tools/gpu/README.md beside the checkout)
# .gpu/src   the code at HEAD (git archive: pipeline, stages, benchmarks) and COMMIT, its commit
# .gpu/stub  dvclive's stand-in, and .gpu/dagrun.py, the DAG runner, both copied from ../shared/tools/gpu
#            (../shared does not travel with the checkout)
# .gpu/proj  (optional) a project copy for dagrun.py
#
# Only .gpu/ is written (ignored by .gitignore); its code, stub, runner and project are replaced on each call,
# its wheels kept.
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
SHARED_GPU=${SHARED_GPU:-$ROOT/../shared/tools/gpu}
PY=${PYTHON:-python3}
G=$ROOT/.gpu
if [ -n "$(git status --porcelain -- pipeline stages benchmarks)" ]; then
  echo "prepare.sh: pipeline/, stages/ or benchmarks/ differ from HEAD; .gpu/src is HEAD's code (commit first)" >&2
fi
rm -rf "$G/src" "$G/stub" "$G/proj" "$G/dagrun.py"
mkdir -p "$G/whl" "$G/src"
git archive HEAD pipeline stages benchmarks pyproject.toml | tar -x -C "$G/src"
git rev-parse HEAD > "$G/src/COMMIT"
cp -r "$SHARED_GPU/stub" "$G/stub"
cp "$SHARED_GPU/dagrun.py" "$G/dagrun.py"
chmod -R u+w "$G/stub" "$G/dagrun.py"
if ! ls "$G"/whl/*.whl > /dev/null 2>&1; then
  $PY -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux_2_28_x86_64 -d "$G/whl" \
    zarr==3.1.6 numcodecs==0.16.6 donfig==0.8.1.post1 google-crc32c==1.9.0 pydantic==2.14.3 \
    pydantic-core==2.50.4 annotated-types==0.8.0 typing-inspection==0.4.5 pycocotools==2.0.11
fi
if [ $# -ge 1 ]; then
  mkdir -p "$G/proj"
  (cd "$G/proj" && PYTHONPATH=$G/src $PY -m pipeline.cli.main profile "$1" --out params.yaml \
     && PYTHONPATH=$G/src $PY -m pipeline.cli.main dag --out dvc.yaml)
fi
du -sh "$G"  # the working tree that travels has at most 64 MiB
