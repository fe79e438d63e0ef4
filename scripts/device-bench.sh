#!/usr/bin/env bash
# The benchmark run on the NVIDIA benchmark machine (see ../shared/GPU.md):
# prebuilt binaries in .gpu/ (tessera, result_load, libvulkan.so.1), no cargo.
# Writes everything under $OUT (or bench-out/device).
#
#   scripts/device-bench.sh [PHASE...]     phases: bench depth farm (default: all three)
#
# `bench` (every suite but depth and farm) fits one 10-minute device call;
# `depth farm` (the depth suite against its depth-32 reference, ~2 min of
# 16 cores, then the farm scaling run, ~3 min) fits another.
set -uo pipefail
PHASES=" ${*:-bench depth farm} "
has() { [[ "$PHASES" == *" $1 "* ]]; }
PHASE=$(echo ${PHASES} | tr ' ' '-')
cd "$(dirname "$0")/.."
OUT=$(realpath -m "${OUT:-bench-out/device}")
mkdir -p "$OUT"
printf '{"file_format_version":"1.0.0","ICD":{"library_path":"/usr/local/nvidia/lib64/libEGL_nvidia.so.0","api_version":"1.3"}}' > /tmp/icd.json
export VK_ICD_FILENAMES=/tmp/icd.json LD_LIBRARY_PATH=$PWD/.gpu:/usr/local/nvidia/lib64${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
T=$PWD/.gpu/tessera
if has bench; then
{
  echo "== machine"; nproc; grep -m1 'model name' /proc/cpuinfo; nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
  echo "== tessera gpus"; "$T" gpus
  echo "== resolution scene, CPU (all cores) and GPU"
  "$T" render examples/resolution.toml -o /tmp/res-cpu.png
  "$T" render examples/resolution.toml --width 1920 --height 1080 -o /tmp/res-cpu-hd.png
  "$T" render examples/resolution.toml --backend gpu -o /tmp/res-gpu.png
  "$T" render examples/resolution.toml --backend gpu --width 1920 --height 1080 -o /tmp/res-gpu-hd.png
} > "$OUT/render.txt" 2>&1
echo "== tessera bench --backend both (every suite but depth and farm)"
timeout 500 "$T" bench resolution samples complexity precision launch --backend both --repeat 3 \
  --out /tmp/bench --cache /tmp/bench-cache > "$OUT/bench-summary.txt" 2> "$OUT/bench-log.txt"
echo "bench exit $?" >> "$OUT/bench-summary.txt"
fi
if has depth; then
echo "== tessera bench depth --backend both (depth-32 f64 reference)"
timeout 400 "$T" bench depth --backend both --repeat 3 \
  --out /tmp/bench --cache /tmp/bench-cache > "$OUT/depth-summary.txt" 2> "$OUT/depth-log.txt"
echo "depth exit $?" >> "$OUT/depth-summary.txt"
fi
if has farm; then
echo "== farm scaling: tessera bench farm (CSV and plots), then scripts/bench-farm.sh (64 spp, with diagnostics) and result throughput"
timeout 150 "$T" bench farm --workers 1,2,4,8 --worker-threads 2 --out /tmp/bench > "$OUT/farm-suite.txt" 2>&1
echo "farm suite exit $?" >> "$OUT/farm-suite.txt"
TESSERA_BIN=$T RESULT_LOAD_BIN=$PWD/.gpu/result_load OUT=/tmp/farm LOAD_SECONDS=5 \
  timeout 330 scripts/bench-farm.sh 8 2 > "$OUT/farm.txt" 2>&1
echo "farm exit $?" >> "$OUT/farm.txt"
echo "== batched result throughput (64 results a message)" >> "$OUT/farm.txt"
"$T" coordinator --listen 127.0.0.1:7999 --data /tmp/load-data > /dev/null 2>&1 &
C=$!; sleep 1
timeout 30 .gpu/result_load http://127.0.0.1:7999 examples/resolution.toml 64 5 64 >> "$OUT/farm.txt" 2>&1
kill $C
fi
# CSVs and plots only: the per-run images are many and large.
tar czf "$OUT/bench-$PHASE.tar.gz" -C /tmp/bench --exclude='*-*x*-s*.png' --exclude='frames-*' --exclude='data-*' .
ls -la "$OUT"
