# Shared set-up of the scripts that run on a lent CUDA machine (bench/gpu_*.sh): sourced, with
# OUT set. Logs to $OUT/run.log; install_gsplat installs gsplat's carried wheel
# (.gpu/gsplat-*.whl) into /tmp/site; compile_kernels builds gsplat's CUDA kernels (background,
# $OUT/gsplat_build.log) and numba's CPU kernels (foreground) at once, and stops the script if
# gsplat did not build; prepare_gpu does both after checking the machine and the imports.
REPO=$PWD
mkdir -p "$OUT"
exec > >(tee -a "$OUT/run.log") 2>&1
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16}
# outside the working tree: what a call carries replaces its paths there, and a warm machine's
# next call then finds the kernels built (61 s on an H100)
export TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-/tmp/egosurg_torch_ext}
stamp() { echo "== $(date +%T) $*"; }

# the machine, gsplat installed, the evaluation's imports checked, both kernels compiled
prepare_gpu() {
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
  python3 -c "import sys, torch; print(sys.version.split()[0], 'torch', torch.__version__)"
  install_gsplat
  stamp "imports"
  python3 -c "import reconstructor.evaluation.cli, reconstructor.evaluation.run, reconstructor.pipeline" || exit 5
  compile_kernels
}

install_gsplat() {
  python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .gpu/gsplat-*.whl || exit 3
  export PYTHONPATH=$REPO:/tmp/site
}

compile_kernels() {
  stamp "compile gsplat's CUDA kernels (background) and numba's CPU kernels (foreground)"
  ( t0=$(date +%s); VERBOSE=1 python3 -c "from gsplat.cuda._backend import _C; assert _C is not None, 'no _C'" \
      > "$OUT/gsplat_build.log" 2>&1; echo "rc=$? after $(( $(date +%s) - t0 )) s" >> "$OUT/gsplat_build.log" ) &
  local build=$!
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
  wait $build
  tail -3 "$OUT/gsplat_build.log"
  if ! ls "$TORCH_EXTENSIONS_DIR"/gsplat_cuda/gsplat_cuda.so > /dev/null 2>&1; then
    grep -m5 -i -B2 -A8 "error" "$OUT/gsplat_build.log" | head -60
    exit 4
  fi
}
