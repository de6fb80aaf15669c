#!/usr/bin/env bash
# A whole case trained on a lent CUDA machine from depth made here (no open3d or OpenCV contrib
# there): `egosurg reconstruct SESSION --every ... --depth-cache DIR` here (any --steps) fills DIR;
# this script installs and compiles gsplat, reruns the case with --device cuda reading DIR, and
# sends the case folder back as .tgz parts (the device tool returns at most 8 files of 16 MiB).
#   usage (repo root): OUT=out SESSION=... CACHE=... bash bench/gpu_case_run.sh [reconstruct args]
set -u
OUT=${OUT:-$PWD/out/gpu_case}
source bench/gpu_common.sh
stamp machine
install_gsplat
compile_kernels
stamp "reconstruct"
timeout ${CASE_TIMEOUT:-150} python3 -c "import sys; from protocol.cli import main; sys.exit(main())" \
  reconstruct "$SESSION" --depth-cache "$CACHE" --device cuda --out /tmp/case "$@" 2>&1 \
  | grep -v " step [0-9]*/\|it/s\]\|s/it\]" | grep -i "case\|depth cache\|warm start\|error\|Traceback\|done\|failed" | tail -40
stamp "reconstruct rc=${PIPESTATUS[0]}"
python3 -c "import sys; from protocol.cli import main; sys.exit(main())" case info /tmp/case
tar czf - --exclude case/.work -C /tmp case | split -b 15M - "$OUT/case.tgz.part"
ls -la "$OUT"
stamp done
