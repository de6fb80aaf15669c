#!/usr/bin/env bash
# One evaluation spread over parallel processes on a lent CUDA machine, in one call: one
# `egosurg evaluate --device cuda` per part manifest of SET (bench/eval_set_parts.py), all at
# once, sharing the GPU and the cores (at 480 px a reconstruction keeps neither busy alone).
# The machine has no open3d and no OpenCV contrib, so each timestamp's depth stage is made here
# first and carried in CACHE (docs/gpu.md). What comes back: $OUT/jobs.tgz (every part's jobs/,
# tables and log: copy the jobs/ together and `egosurg evaluate <whole set> --resume` writes
# the tables, docs/evaluation.md "Spreading a run") and $OUT/pictures.tgz (the
# first PICTURES, 24, of the renders: a call brings back at most 16 MiB a file).
#   usage (repo root): OUT=out_dir SET=.gpu/egoA CACHE=.gpu/dc_A \
#                      bash bench/gpu_eval_parts.sh [the evaluate options, the same for every part]
# DEVICE=cpu runs the same plumbing on the CPU (no gsplat), to check it before a lease.
set -u
OUT=${OUT:-$PWD/out/gpu_parts}
SET=${SET:?name the folder that holds the part manifests (eval_set.part-*.toml)}
CACHE=${CACHE:?name the depth cache folder made for SET}
DEVICE=${DEVICE:-cuda}
source bench/gpu_common.sh
stamp machine
if [ "$DEVICE" = cuda ]; then
  prepare_gpu
  PY=python3
else
  PY=${PY:-.venv/bin/python}
fi
parts=("$SET"/eval_set.part-*.toml)
n=${#parts[@]}
threads=$(( $(nproc) / n )); [ "$threads" -lt 1 ] && threads=1
mkdir -p "$OUT/parts"
stamp "evaluate: $n parts at once, $threads threads each"
pids=()
for m in "${parts[@]}"; do
  name=$(basename "$m" .toml); name=${name#eval_set.part-}
  OMP_NUM_THREADS=$threads NUMBA_NUM_THREADS=$threads timeout "${EVAL_TIMEOUT:-420}" \
    $PY -c "import sys; from protocol.cli import main; sys.exit(main())" \
    evaluate "$m" --out "$OUT/parts/$name" --depth-cache "$CACHE" --device "$DEVICE" "$@" \
    > "$OUT/parts/$name.log" 2>&1 &
  pids+=($!)
done
for i in "${!pids[@]}"; do
  wait "${pids[$i]}"; rc=$?
  name=$(basename "${parts[$i]}" .toml)
  echo "${name#eval_set.part-}: rc=$rc, $(ls "$OUT/parts/${name#eval_set.part-}/jobs/"*.json 2>/dev/null | wc -l) job(s) recorded"
  grep -h "Error\|error:" "$OUT/parts/${name#eval_set.part-}.log" | grep -v " step " | tail -3
done
stamp "evaluate done"
grep -h "evaluation done\|^.*INFO.*\[[0-9]*/[0-9]*\] " "$OUT"/parts/*.log | sed 's/^.*INFO [a-z._]*: //' | tail -60
( cd "$OUT" && tar czf jobs.tgz --exclude='*.png' parts && find parts -name '*.png' | sort | head -${PICTURES:-24} | tar czf pictures.tgz -T -; ls -la jobs.tgz pictures.tgz )
stamp "done"
