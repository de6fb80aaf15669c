#!/usr/bin/env bash
# The GPU backend's checks on a lent CUDA machine, in one call (BENCHMARKS.md, "GPU backend"):
# gsplat's CUDA kernels JIT-compiled for this GPU, the `gpu` tests, then bench/bench_gpu.py.
# Prepared here (no open3d there): .gpu/scene.npz (python -m tests.gpu_scene .gpu/scene.npz) and
# gsplat's wheel in .gpu/; the CPU reference is bench/results/gpu_cpu_reference.json.
#   usage (repo root): OUT=out_dir bash bench/gpu_device_run.sh
set -u
OUT=${OUT:-$PWD/out/gpu}
source bench/gpu_common.sh
export EGOSURG_GPU_SCENE=$REPO/.gpu/scene.npz
stamp machine
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -c "import sys, torch, numba, numpy; print(sys.version.split()[0], 'torch', torch.__version__, 'cuda', torch.version.cuda, 'numba', numba.__version__, 'numpy', numpy.__version__)"
nvcc --version | tail -2
nproc

stamp "install gsplat (pure Python; its CUDA code compiles on first use)"
install_gsplat
compile_kernels
SO=$TORCH_EXTENSIONS_DIR/gsplat_cuda/gsplat_cuda.so
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
