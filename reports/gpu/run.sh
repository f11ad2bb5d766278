#!/bin/bash
# issue 43 item 5: the plateau recipe at 384^2 (reduced-strong data sizes = the paper's 270/60/3x60), Plain,
# GeoDistill-Refine, continuation and the supervised ceiling at seeds 42/3407/2026, all runs in parallel on one GPU
cd "$(dirname "$0")/.."
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .gpu/whl/*.whl || exit 3
export PYTHONPATH=/tmp/site:$PWD/.gpu/stub:$PWD/.gpu/src PYTHONUNBUFFERED=1 SOURCE_DATE_EPOCH=315532800 GD_PAR=12
{ date -u; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; nproc; python3 -c "import torch; print(torch.__version__, torch.version.cuda)"; echo "code: main at 9f5a10d (git archive)"; } > $OUT/card.txt 2>&1
python3 .gpu/dagrun.py .gpu/proj ${DEADLINE:-500} > $OUT/dagrun.log 2>&1
cd .gpu/proj
tar czf $OUT/results.tgz --exclude='*.zarr' --exclude='*.safetensors' logs reports artifacts 2>/dev/null
ls -la $OUT
