#!/bin/bash
# issue 43 item 4: the data-scaling curve at 64^2 under the plateau recipe (Plain and the ceiling, seed 42), on the GPU
cd "$(dirname "$0")/.."
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .gpu/whl/*.whl || exit 3
export PYTHONPATH=/tmp/site:$PWD/.gpu/stub:$PWD/.gpu/src PYTHONUNBUFFERED=1 SOURCE_DATE_EPOCH=315532800 OMP_NUM_THREADS=1
{ date -u; nvidia-smi --query-gpu=name,driver_version --format=csv,noheader; python3 -c "import torch; print(torch.__version__)"; } > $OUT/card.txt 2>&1
cd .gpu/src
for spec in "2 8 1700" "4 17 378" "9 30 100"; do
  set -- $spec; n=$(($1*$2))
  timeout ${LIMIT:-165} python3 -m benchmarks.study_recipe --profile reduced --resolution 64 --workdir /tmp/s/n$n \
    --train-spacecraft $1 --train-views $2 --set train.recipe=plateau --epochs $3 --variants paper --seeds 42 \
    --jobs 2 --threads 1 --device cuda --out $OUT/n$n.json > /tmp/n$n.log 2>&1 &
done
wait
for n in 16 68 270; do echo "== n$n"; tail -c 1500 /tmp/n$n.log; done > $OUT/logs.txt
ls -la $OUT
