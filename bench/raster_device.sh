#!/bin/bash
# One call on the GPU machine: wheels, our build and gsplat's JIT build in parallel, the GPU
# tests, then the benchmark. Logs and results under $OUT. Run from the repo root with .whl and
# .data carried (bash /work/shared/device/wheels.sh makes .whl).
set -o pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 PYTHONUNBUFFERED=1
export TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-/tmp/torch_ext}
# a carried gsplat build (.extcache/ext.tgz.*, made by bench/device_bench.sh SAVE_CACHE=1) saves its ~90 s
if [ -f .extcache/ext.tgz.aa ] && [ ! -d $TORCH_EXTENSIONS_DIR/gsplat_cuda ]; then
  find /tmp/site/gsplat -exec touch -h -d '2001-01-01' {} +
  cat .extcache/ext.tgz.* | tar xzf - -C $(dirname $TORCH_EXTENSIONS_DIR) --wildcards 'torch_ext/gsplat_cuda*'
fi
nvidia-smi > $OUT/gpu.txt 2>&1
python3 -c "import torch; print(torch.__version__, torch.version.cuda)" >> $OUT/gpu.txt
t0=$(date +%s)
(time python3 -c "from virgi_ns.raster import cuda; cuda.build(verbose=True)") > $OUT/build_ours.log 2>&1 &
(time python3 -c "from gsplat.cuda._backend import _C; print(_C)") > $OUT/build_gsplat.log 2>&1 &
wait
echo "builds: $(( $(date +%s) - t0 )) s"; tail -n 3 $OUT/build_ours.log $OUT/build_gsplat.log
python3 -m pytest ${RASTER_TESTS:-tests/test_raster_cuda.py tests/test_raster_reference.py} -q -rf --tb=short -p no:cacheprovider ${PYTEST_ARGS:-} > $OUT/tests.log 2>&1
echo "tests rc=$? ($(( $(date +%s) - t0 )) s)"; grep -E "passed|failed|error" $OUT/tests.log | tail -5
python3 bench/raster.py --out $OUT/bench ${BENCH_ARGS:-} 2>$OUT/bench.log
echo "bench rc=$? ($(( $(date +%s) - t0 )) s)"
