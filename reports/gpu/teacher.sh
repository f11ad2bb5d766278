#!/bin/bash
# issue 58 item 4: the real-size SAM 3 teacher on the GPU (random weights: time and memory only), bf16, the vision
# encoder compiled, batch 1-32: per batch size its first call (the compilation), steady ms per image and peak
# memory above the model (benchmarks/bench_teacher.py --batch-sweep; its logic is tested on a CPU in
# tests/benchmarks/test_bench_teacher_roofline.py).  Prepared, not yet run: no figure from it is published.
# About 6 minutes on an H200 is the estimate (a 3.4 GB checkpoint written once, six compilations); LIMIT caps it.
cd "$(dirname "$0")/.."
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .gpu/whl/*.whl || exit 3
export PYTHONPATH=/tmp/site:$PWD/.gpu/stub:$PWD/.gpu/src PYTHONUNBUFFERED=1 SOURCE_DATE_EPOCH=315532800
{ date -u; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader; python3 -c "import torch, transformers; print(torch.__version__, torch.version.cuda, transformers.__version__)"; } > $OUT/card.txt 2>&1
cd .gpu/src
timeout ${LIMIT:-480} python3 -m benchmarks.bench_teacher --batch-sweep 1,2,4,8,16,32 --size real --device cuda \
  --dtype bf16 --compile --images 32 --resolution 256 --repeats 3 --json $OUT/teacher-gpu.json > $OUT/teacher.log 2>&1
echo "exit $?" >> $OUT/teacher.log
ls -la $OUT
