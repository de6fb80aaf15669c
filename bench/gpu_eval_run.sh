#!/usr/bin/env bash
# Table 3B (temporal stability) at 10 timestamps on a lent CUDA machine, in one call.
# That machine has no open3d and no OpenCV contrib modules (SGBM+WLS), so the depth stage is made
# here first and carried: `egosurg evaluate ... --depth-cache .gpu/depthcache` with any methods
# (depth-reprojection alone makes every timestamp's entry in ~5 s each) fills it; the GPU run reads
# it and trains, renders and scores with `--device cuda`. Needs .gpu/gsplat-*.whl and the
# evaluation set (out/evalset10) carried. CACHE names another depth cache folder (carry it too).
#   usage (repo root): OUT=out_dir EVALSET=out/evalset10 [CACHE=.gpu/depthcache] \
#                      bash bench/gpu_eval_run.sh [extra evaluate args]
set -u
OUT=${OUT:-$PWD/out/gpu_eval}
EVALSET=${EVALSET:-out/evalset10}
CACHE=${CACHE:-.gpu/depthcache}
source bench/gpu_common.sh
stamp machine
prepare_gpu
stamp "evaluate"
timeout ${EVAL_TIMEOUT:-480} python3 -c "import sys; from protocol.cli import main; sys.exit(main())" \
  evaluate "$EVALSET" --out "$OUT/eval" --depth-cache "$CACHE" --device cuda \
  --write-doc "$OUT/eval/EVALUATION.md" "$@" 2>&1 | grep -v " step [0-9]*/" \
  | grep -v "stereo depth valid\|warm start: kept" | tee "$OUT/evaluate.log" | tail -60
stamp "done rc=${PIPESTATUS[0]}"
