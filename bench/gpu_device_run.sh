#!/usr/bin/env bash
# The GPU backend's checks on a lent CUDA machine, in one call (BENCHMARKS.md, "GPU backend"):
# gsplat's CUDA kernels JIT-compiled for this GPU, the `gpu` tests, then bench/bench_gpu.py.
# Prepared here (no open3d there): .gpu/scene.npz (python -m tests.gpu_scene .gpu/scene.npz) and
# gsplat's wheel in .gpu/; the CPU reference is bench/results/gpu_cpu_reference.json.
#   usage (repo root): OUT=out_dir bash bench/gpu_device_run.sh
set -u
REPO=$PWD
OUT=${OUT:-$REPO/out/gpu}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/run.log") 2>&1
export PYTHONUNBUFFERED=1 EGOSURG_GPU_SCENE=$REPO/.gpu/scene.npz
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16}
export TORCH_EXTENSIONS_DIR=$REPO/.gpu/ext
stamp() { echo "== $(date +%T) $*"; }
stamp machine
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -c "import sys, torch, numba, numpy; print(sys.version.split()[0], 'torch', torch.__version__, 'cuda', torch.version.cuda, 'numba', numba.__version__, 'numpy', numpy.__version__)"
nvcc --version | tail -2
nproc

stamp "install gsplat (pure Python; its CUDA code compiles on first use)"
python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .gpu/gsplat-*.whl || exit 3
export PYTHONPATH=$REPO:/tmp/site

stamp "compile gsplat's CUDA kernels (background) and numba's CPU kernels (foreground)"
( t0=$(date +%s); VERBOSE=1 python3 -c "from gsplat.cuda._backend import _C; assert _C is not None, 'no _C'" \
    > "$OUT/gsplat_build.log" 2>&1; echo "rc=$? after $(( $(date +%s) - t0 )) s" >> "$OUT/gsplat_build.log" ) &
BUILD=$!
python3 - <<'PY'
import time, torch
t0 = time.perf_counter()
from tests.reconstructor.test_raster import make_scene
from reconstructor.raster import rasterize, RasterConfig
s = make_scene(50, 0)
p = {k: (v.requires_grad_(True) if k in ("means_m", "colors") else v) for k, v in s.items()}
rasterize(**p, config=RasterConfig()).image.sum().backward()
from reconstructor.splats.image_loss import image_loss
x = torch.rand(40, 60, 3, requires_grad=True)
image_loss(x, torch.rand(40, 60, 3), torch.ones(40, 60), 0.2)[0].backward()
print(f"numba kernels compiled in {time.perf_counter() - t0:.0f} s")
PY
wait $BUILD
tail -3 "$OUT/gsplat_build.log"
SO=$(ls "$TORCH_EXTENSIONS_DIR"/gsplat_cuda/gsplat_cuda.so 2>/dev/null)
if [ -z "$SO" ]; then grep -m5 -i -B2 -A8 "error" "$OUT/gsplat_build.log" | head -60; exit 4; fi
ls -la "$SO"
(cd "$TORCH_EXTENSIONS_DIR/gsplat_cuda" && tar czf - gsplat_cuda.so build.ninja .ninja_log .ninja_deps 2>/dev/null) \
  | split -b 15M - "$OUT/gsplat_cuda.tgz.part"

if [ -n "${SKIP_TESTS:-}" ]; then stamp "gpu tests skipped"; else
stamp "gpu tests"
timeout 240 python3 -m pytest -q -s -m gpu -p no:cacheprovider -o addopts="" \
  tests/reconstructor/test_raster_gsplat.py tests/reconstructor/test_gsplat_train.py --durations=5 \
  2>&1 | tee "$OUT/pytest_gpu.log" | tail -40
fi

if [ -n "${SKIP_BENCH:-}" ]; then stamp "bench skipped"; exit 0; fi
stamp "bench"
timeout 400 python3 bench/bench_gpu.py --compare ${BENCH_ARGS:-} \
  --reference bench/results/gpu_cpu_reference.json --json "$OUT/bench_gpu.json" 2>&1 \
  | grep -v "step [0-9]*/" | tee "$OUT/bench_gpu.log" | tail -40
stamp done
