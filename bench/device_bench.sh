#!/bin/bash
# The GPU benchmarks (raster / train / several GPUs / export / edit / demo geometry) in calls on the GPU machine.
# Run from the repo root with .whl (../shared/device/wheels.sh) and .data/beercan carried, or with .data filled by
# bench/device_data.sh (the wheels and the captures packed to fit the 64 MiB a call carries);
# STAGE picks the work: "suite" (the GPU suite and the splat path's wall), "raster" (the rasterizer's GPU tests, then bench/raster.py), "train" (bench/train.py),
# "multi" (bench/multi_gpu.py), "rest" (export, edit, demo geometry), any single one of export|edit|demo, or "none"
# (install and build only, for a command of its own after it). Runs go under /tmp/runs (kept while the machine is warm);
# tables, JSON, pictures and logs are packed into $OUT. Environment knobs: STEPS, COLOUR_STEPS,
# DEMO_STEPS, DEMO_VARIANTS ("downscale:cap ..."), DEMO_FINETUNE, EDIT_SCENES (rows of the evaluation set), SEED (one
# run set, or several side by side: "69 70"),
# EDIT_TIMEOUT (default: what CALL_BUDGET leaves after the build, less the merge), EDIT_COLOUR_STEPS, EDIT_ARGS (more bench/edit.py flags, e.g. --variants), TRAIN_ARGS (more bench/train.py
# flags), TRAIN_TIMEOUT, RASTER_TESTS, PYTEST_ARGS, RASTER_ARGS (more bench/raster.py flags). With several GPUs the edit rows run side by side, one process per GPU (a log each); the
# edit results come back as edit_results_s<SEED>.tgz, their logs as edit_logs.tgz.
set -o pipefail
export TORCH_EXTENSIONS_DIR=/tmp/torch_ext TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=$(nproc) PYTHONUNBUFFERED=1
export PYTHONPATH=/tmp/site:$PWD NERFSTUDIO_METHOD_CONFIGS="virgi=method_configs.virgi:virgi_method"
STEPS=${STEPS:-7000}; COLOUR_STEPS=${COLOUR_STEPS:-3000}; DEMO_STEPS=${DEMO_STEPS:-15000}
RUNS=/tmp/runs; mkdir -p $RUNS
t0=$(date +%s)
el() { echo "[$(( $(date +%s) - t0 )) s] $*"; }

if [ ! -f /tmp/site/.installed ]; then
  if [ -f .data/site.txz ]; then  # the wheels' files, packed by bench/device_data.sh to fit the carry
    mkdir -p /tmp/site && tar xJf .data/site.txz -C /tmp/site || exit 1
  else
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  fi
  # a carried build cache (.extcache/ext.tgz.*) is reused when the sources look older than it
  if [ -f .extcache/ext.tgz.aa ] && [ ! -d $TORCH_EXTENSIONS_DIR ]; then
    # gsplat's build only (it never changes); ours always rebuilds from the working tree (~25 s)
    find /tmp/site/gsplat -exec touch -h -d '2001-01-01' {} +
    cat .extcache/ext.tgz.* | tar xzf - -C /tmp --wildcards 'torch_ext/gsplat_cuda*' && el "restored gsplat build"
    # a later call on this machine must not skip our build either
    (cd /tmp/torch_ext && ls)
  fi
  touch /tmp/site/.installed
fi
rm -f .data/site.txz
if [ -f .data/sparse.txz ]; then  # COLMAP folders packed by bench/device_data.sh
  tar xJf .data/sparse.txz -C .data && rm .data/sparse.txz || exit 1
fi
(nvidia-smi --query-gpu=name,driver_version --format=csv; nvidia-smi topo -m) > $OUT/gpu.txt 2>&1

if [ ! -f $TORCH_EXTENSIONS_DIR/.built ] || [ -n "${REBUILD_OURS:-}" ]; then
  (time python3 -c "from virgi_ns.raster import cuda; cuda.build(verbose=False)") > $OUT/build_ours.log 2>&1 &
  (time python3 -c "from gsplat.cuda._backend import _C; print(_C)") > $OUT/build_gsplat.log 2>&1 &
  wait
  el "builds"; tail -n 4 $OUT/build_ours.log $OUT/build_gsplat.log
  touch $TORCH_EXTENSIONS_DIR/.built
  if [ "${SAVE_CACHE:-0}" = 1 ]; then  # gsplat's build, for later calls to carry as .extcache/
    (cd /tmp && tar czf - torch_ext/gsplat_cuda*) | split -b 15m - $OUT/ext.tgz. ; ls -la $OUT
  fi
fi

stage() { case " $STAGE " in *" $1 "*) return 0;; esac; [ "$STAGE" = rest ] && [ "$1" != train ] && [ "$1" != multi ] \
  && [ "$1" != raster ]; }

if stage raster; then
  # the rasterizer against its reference and gsplat (the GPU tests), then its benchmark
  python3 -m pytest ${RASTER_TESTS:-tests/test_raster_cuda.py tests/test_raster_reference.py} -q -rf --tb=short \
    -p no:cacheprovider ${PYTEST_ARGS:-} > $OUT/raster_tests.log 2>&1
  el "raster tests rc=$?"; grep -E "passed|failed|error" $OUT/raster_tests.log | tail -5
  python3 bench/raster.py --out $RUNS/raster ${RASTER_ARGS:-} > $OUT/raster.log 2>&1; el "raster bench rc=$?"
  tail -n 30 $OUT/raster.log
  cp $RUNS/raster/*.json $OUT/ 2>/dev/null
fi

if stage suite; then
  # the GPU suite (pytest -m gpu) without its slow tests, then each bundled splat from `ns-train virgi --data SPLAT
  # splat` to a trained run (views rendered into an empty cache; bytecode cached first, as an install keeps it), then
  # the slow GPU tests while CALL_BUDGET lasts; .data carries beercan and splats/ (a module this machine cannot
  # import, such as the CPU tests' independent PLY reader, is left uncollected)
  export VIRGI_SHARED_DATA=$PWD/.data PYTHONPYCACHEPREFIX=/tmp/pycache; unset PYTHONDONTWRITEBYTECODE
  python3 -m pytest -m "gpu and not slow" -q -rfE --tb=short -p no:cacheprovider --continue-on-collection-errors ${PYTEST_ARGS:-} > $OUT/gpu_suite.log 2>&1
  el "GPU suite rc=$?"; grep -E "^(FAILED|ERROR)|passed|failed" $OUT/gpu_suite.log | tail -n 30
  python3 -c "import nerfstudio.scripts.train, method_configs.virgi, virgi_ns.data.splat, virgi_ns.nerfstudio.model, gsplat"
  for s in .data/splats/*.compressed.ply; do
    n=$(basename $s .compressed.ply); rm -rf /tmp/splat_cache /tmp/splat_runs
    s0=$(date +%s.%N)
    VIRGI_NS_CACHE=/tmp/splat_cache NERFSTUDIO_DATAPARSER_CONFIGS="splat=virgi_ns.data.splat:splat_dataparser" \
      python3 -c "from nerfstudio.scripts.train import entrypoint; entrypoint()" virgi --data $s --vis tensorboard \
      --output-dir /tmp/splat_runs splat > $OUT/splat_train_$n.log 2>&1
    rc=$?; el "splat $n: ns-train to a trained run $(python3 -c "import sys; print(f'{float(sys.argv[2]) - float(sys.argv[1]):.1f}')" $s0 $(date +%s.%N)) s, rc=$rc"
  done
  timeout $(( ${CALL_BUDGET:-585} - $(date +%s) + t0 )) python3 -m pytest -m "gpu and slow" -q -rfE --tb=short --continue-on-collection-errors \
    -p no:cacheprovider > $OUT/gpu_suite_slow.log 2>&1
  el "slow GPU tests rc=$?"; grep -E "^(FAILED|ERROR)|passed|failed" $OUT/gpu_suite_slow.log | tail -n 10
fi

if stage multi; then
  # ns-train virgi on N GPUs against one (bench/multi_gpu.py): WORLDS (default "1 2"), SEED (default 42)
  # a usual install keeps compiled bytecode; this machine's interpreter writes none, so a cache stands in
  # for it (filled here, unmeasured), or every process of every run would compile what it imports
  export PYTHONPYCACHEPREFIX=/tmp/pycache; unset PYTHONDONTWRITEBYTECODE
  PYTHONPATH=bench:$PYTHONPATH python3 -c "import multi_gpu, train, common.training, nerfstudio.scripts.train, gsplat
import method_configs.virgi, virgi_ns.nerfstudio.model, virgi_ns.raster.cuda"; el "bytecode cache filled"
  el "multi-GPU bench: worlds ${WORLDS:-1 2}, seeds ${SEED:-42}, $STEPS + ${MULTI_COLOUR_STEPS:-1000} steps"
  timeout ${MULTI_TIMEOUT:-$(( ${CALL_BUDGET:-585} - $(date +%s) + t0 ))} python3 bench/multi_gpu.py --data $PWD/.data --out $RUNS/multi --steps $STEPS \
    --colour-steps ${MULTI_COLOUR_STEPS:-1000} --worlds ${WORLDS:-1 2} --seeds ${SEED:-42} > $OUT/multi_gpu.log 2>&1
  el "multi rc=$?"; grep -v "^\s*$" $OUT/multi_gpu.log | tail -n 40
  cp $RUNS/multi/results.json $OUT/multi_gpu_results.json 2>/dev/null
fi

if stage train; then
  el "train bench: $STEPS + $COLOUR_STEPS steps"
  timeout ${TRAIN_TIMEOUT:-3600} python3 bench/train.py --data $PWD/.data --out $RUNS/train --steps $STEPS --colour-steps $COLOUR_STEPS ${TRAIN_ARGS:-} \
    > $OUT/train.log 2>&1; el "train rc=$?"
  tail -n 30 $OUT/train.log
  (cd $RUNS/train && tar czf $OUT/train_results.tgz results.json *.png) 2>/dev/null
fi
CFG=$RUNS/train/runs/beercan-virgi/virgi/run/config.yml
if stage edit; then
  # the evaluation set (bench/edit.py): EDIT_SCENES picks rows (default all), SEED a run set, EDIT_ARGS more flags.
  # SEED may name several run sets ("69 70"): they run side by side, each on its share of the GPUs.
  # A run set's rows run side by side over its GPUs, one process per GPU (the rows of one capture together,
  # bench/common/evalset.py split_for_devices), and their results are merged into one table per run set.
  SEEDS=(${SEED:-42}); NS=${#SEEDS[@]}
  [ "$NS" -ge 1 ] || SEEDS=(42) NS=1
  [ "$(printf '%s\n' "${SEEDS[@]}" | sort -u | wc -l)" -eq "$NS" ] || { echo "SEED names a run set twice: ${SEEDS[*]}"; exit 2; }
  el "edit bench: ${EDIT_SCENES:-all scenes}, run set seed(s) ${SEEDS[*]}"
  rm -rf $RUNS/edit $RUNS/edit_gpu* $RUNS/edit_s* $RUNS/edit_logs  # an earlier call's results must not travel
  LOGS=$RUNS/edit_logs; mkdir -p $LOGS  # packed into one file at the end: at most 8 files come back from $OUT
  NG=$(nvidia-smi --query-gpu=index --format=csv,noheader 2>/dev/null | wc -l); [ "$NG" -ge 1 ] || NG=1
  G=$(( NG / NS )); [ "$G" -ge 1 ] || { echo "$NS run sets need at least $NS GPUs; this machine has $NG"; exit 2; }
  edit_rows() {  # GPU, run set seed, output folder, rows... (none: the whole set)
    local gpu=$1 seed=$2 out=$3; shift 3
    # each run set trains under its own folder: two run sets must not write one synthetic capture at once
    CUDA_VISIBLE_DEVICES=$gpu OMP_NUM_THREADS=$(( $(nproc) / NG > 0 ? $(nproc) / NG : 1 )) timeout ${EDIT_TIMEOUT:-$(( ${CALL_BUDGET:-585} - 25 - $(date +%s) + t0 ))} python3 bench/edit.py \
      --data $PWD/.data ${1:+--scenes} "$@" --train-out $RUNS/edit_runs_s$seed --seed $seed --geometry-steps $STEPS \
      --colour-steps ${EDIT_COLOUR_STEPS:-1000} --out $out ${EDIT_ARGS:-}
  }
  # (--million and the pick latency run in every process, beside the others: time them on one GPU)
  pids=(); names=()
  for j in "${!SEEDS[@]}"; do
    seed=${SEEDS[$j]}; i=0
    while read -r rows; do
      g=$(( j * G + i )); echo "GPU $g: run set $seed: ${rows:-all rows}"
      edit_rows $g $seed $RUNS/edit_s${seed}_gpu$i $rows > $LOGS/edit_s${seed}_gpu$i.log 2>&1 < /dev/null &
      pids+=($!); names+=("run set $seed, GPU $g"); i=$((i + 1))
    done < <(PYTHONPATH=bench:$PYTHONPATH python3 -c "import sys; from common.evalset import split_for_devices as s
for p in s(sys.argv[2:], int(sys.argv[1])): print(' '.join(p))" $G ${EDIT_SCENES:-})
  done
  for k in "${!pids[@]}"; do  # a process cut short or failed is said, and its rows are missing below
    wait ${pids[$k]}; el "edit ${names[$k]} rc=$?"
  done
  for d in $RUNS/edit_s*_gpu*; do [ -f $d/results.json ] || echo "${d##*/}: no results (its rows are missing)"; done
  for seed in "${SEEDS[@]}"; do
    ls $RUNS/edit_s${seed}_gpu*/results.json > /dev/null 2>&1 || { echo "run set $seed: no results"; continue; }
    python3 bench/edit.py --merge $RUNS/edit_s${seed}_gpu*/results.json --out $RUNS/edit_s$seed > $LOGS/edit_s$seed.log 2>&1
    el "merge run set $seed rc=$?"; tail -n 60 $LOGS/edit_s$seed.log
    cp $RUNS/edit_s${seed}_gpu*/*.png $RUNS/edit_s$seed/ 2>/dev/null
    # pictures as JPEG (the README's form): a run set's PNGs can pass the 16 MiB a file that comes back
    (cd $RUNS/edit_s$seed && python3 -c "import sys, cv2
for f in sys.argv[1:]: cv2.imwrite(f[:-4] + '.jpg', cv2.imread(f), [cv2.IMWRITE_JPEG_QUALITY, 90])" *.png 2>/dev/null \
      && tar czf $OUT/edit_results_s$seed.tgz *.json *.jpg || tar czf $OUT/edit_results_s$seed.tgz *.json *.png) 2>/dev/null
  done
  (cd $LOGS && tar czf $OUT/edit_logs.tgz *.log)
fi
if stage export; then
  el "export bench"
  python3 bench/export.py --load-config $CFG --out $RUNS/export > $OUT/export.log 2>&1; el "export rc=$?"
  tail -n 30 $OUT/export.log
  cp $RUNS/export/export_results.json $OUT/ 2>/dev/null
fi
if stage demo; then
  # DEMO_VARIANTS: space-separated downscale:cap pairs, one geometry file each
  for v in ${DEMO_VARIANTS:-2:60000}; do
    ds=${v%%:*}; cap=${v##*:}
    el "demo geometry: $DEMO_STEPS steps, 1/$ds, cap $cap"
    python3 scripts/train_demo_geometry.py --source $PWD/.data/beercan --steps $DEMO_STEPS --downscale $ds --cap $cap \
      --finetune-steps ${DEMO_FINETUNE:-3000} --out $RUNS/geometry_ds${ds}_${cap}.ply > $OUT/demo_ds${ds}_${cap}.log 2>&1
    el "demo rc=$?"; grep -a "wrote\|kept\|fine-tuned\|Error" $OUT/demo_ds${ds}_${cap}.log | tail -n 5
    cp $RUNS/geometry_ds${ds}_${cap}.ply $OUT/ 2>/dev/null
  done
fi
el done
