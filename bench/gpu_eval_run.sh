#!/usr/bin/env bash
# Table 3B (temporal stability) at 10 timestamps on a lent CUDA machine, in one call.
# That machine has no open3d and no OpenCV contrib modules (SGBM+WLS), so the depth stage is made
# here first and carried: `egosurg evaluate ... --depth-cache .gpu/depthcache` with any methods
# (depth-reprojection alone makes every timestamp's entry in ~5 s each) fills it; the GPU run reads
# it and trains, renders and scores with `--device cuda`. Needs .gpu/gsplat-*.whl and the
# evaluation set (out/evalset10) carried.
#   usage (repo root): OUT=out_dir EVALSET=out/evalset10 bash bench/gpu_eval_run.sh [extra evaluate args]
set -u
REPO=$PWD
OUT=${OUT:-$REPO/out/gpu_eval}
EVALSET=${EVALSET:-out/evalset10}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/run.log") 2>&1
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16}
export TORCH_EXTENSIONS_DIR=$REPO/.gpu/ext
stamp() { echo "== $(date +%T) $*"; }
stamp machine
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
python3 -c "import sys, torch; print(sys.version.split()[0], 'torch', torch.__version__)"
python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .gpu/gsplat-*.whl || exit 3
export PYTHONPATH=$REPO:/tmp/site
stamp "imports"
python3 -c "import reconstructor.evaluation.cli, reconstructor.evaluation.run, reconstructor.pipeline" || exit 5
stamp "compile gsplat (background) and numba kernels (foreground)"
( python3 -c "from gsplat.cuda._backend import _C; assert _C is not None" > "$OUT/gsplat_build.log" 2>&1;
  echo "rc=$?" >> "$OUT/gsplat_build.log" ) &
BUILD=$!
python3 - <<'PY'
import time, torch
t0 = time.perf_counter()
from tests.reconstructor.test_raster import make_scene
from reconstructor.raster import rasterize, RasterConfig
s = make_scene(50, 0)
p = {k: (v.requires_grad_(True) if k in ("means_m", "colors") else v) for k, v in s.items()}
rasterize(**p, config=RasterConfig()).image.sum().backward()
print(f"numba kernels compiled in {time.perf_counter() - t0:.0f} s")
PY
wait $BUILD
tail -2 "$OUT/gsplat_build.log"
stamp "evaluate"
timeout ${EVAL_TIMEOUT:-480} python3 -c "import sys; from protocol.cli import main; sys.exit(main())" \
  evaluate "$EVALSET" --out "$OUT/eval" --depth-cache .gpu/depthcache --device cuda \
  --write-doc "$OUT/eval/EVALUATION.md" "$@" 2>&1 | grep -v " step [0-9]*/" \
  | grep -v "stereo depth valid\|warm start: kept" | tee "$OUT/evaluate.log" | tail -60
stamp "done rc=${PIPESTATUS[0]}"
