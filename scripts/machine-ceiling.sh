#!/usr/bin/env bash
# How well does this machine itself scale? Runs K independent local renders
# (no farm) at once and reports each one's wall time against a lone run. The
# farm's parallel efficiency cannot beat this ceiling (shared cores,
# hyper-threads, memory bandwidth, turbo).
#   scripts/machine-ceiling.sh [THREADS] [K...]
set -uo pipefail
cd "$(dirname "$0")/.."
T=${TESSERA:-$PWD/.gpu/tessera}
THREADS=${1:-2}; shift || true
KS=${*:-1 2 4 8}
SCENE=examples/resolution.toml
ARGS="--width 1920 --height 1080 --samples 16"
echo "== machine"; nproc; lscpu | grep -E 'Model name|Thread\(s\) per core|Core\(s\) per socket|Socket\(s\)|NUMA node\(s\)|L3' 
echo "scene: $SCENE $ARGS, $THREADS threads per render"
printf '%4s %10s %10s %10s\n' K mean_s max_s ceiling
base=""
for k in $KS; do
  pids=()
  for i in $(seq 1 "$k"); do
    ( s=$EPOCHREALTIME; "$T" render $SCENE $ARGS --threads "$THREADS" -o /tmp/ceil-$i.png >/dev/null 2>&1; awk -v s="$s" -v e="$EPOCHREALTIME" 'BEGIN { printf "%.3f\n", e - s }' > /tmp/ceil-$i.t ) & pids+=($!)
  done
  wait "${pids[@]}"
  mean=$(cat $(seq -f /tmp/ceil-%g.t 1 "$k") | awk '{s+=$1} END {printf "%.3f", s/NR}')
  max=$(cat $(seq -f /tmp/ceil-%g.t 1 "$k") | sort -n | tail -1)
  [ -z "$base" ] && base=$mean
  awk -v k="$k" -v m="$mean" -v x="$max" -v b="$base" 'BEGIN { printf "%4s %10.3f %10.3f %9.1f%%\n", k, m, x, 100 * b / x }'
done
