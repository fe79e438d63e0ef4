#!/usr/bin/env bash
# Diagnostics for the farm's scaling on a many-core machine (device run),
# in parts (default: all):
#   ceiling  CPU topology; K independent local renders at once (no farm),
#            unpinned and pinned one per guest core: how the machine scales
#   pairs    a one-thread render on CPU 0 beside one on CPU j, for each j:
#            which CPUs slow each other down
#   split    the farm's workload without the farm: K concurrent local
#            2-thread renders of 64/K samples each (1920x1080), so the
#            K-worker farm's time can be set against the machine's own
#   farm     scripts/bench-farm.sh (64 spp, COUNTS workers of 2 threads),
#            the workers' logs kept for scripts/farm-timeline.py
#   scripts/farm-probe.sh OUTDIR [PART...]
set -uo pipefail
cd "$(dirname "$0")/.."
OUTD=${1:?outdir}; shift; mkdir -p "$OUTD"
PARTS=" ${*:-ceiling pairs split farm} "
has() { [[ "$PARTS" == *" $1 "* ]]; }
T=${TESSERA:-$PWD/.gpu/tessera}
timed() { local s=$EPOCHREALTIME; "$@" >/dev/null 2>&1; awk -v s="$s" -v e="$EPOCHREALTIME" 'BEGIN { printf "%.3f", e - s }'; }
if has ceiling; then
{
echo "== topology"; nproc; lscpu; lscpu -e
echo "== ceiling, unpinned"
TESSERA=$T scripts/machine-ceiling.sh 2 1 2 4 8
echo "== ceiling, pinned: one 2-thread render per guest core"
mapfile -t cores < <(lscpu -p=CORE,CPU | grep -v '^#' | sort -t, -k1,1n -k2,2n | awk -F, '{a[$1]=a[$1] (a[$1]==""?"":",") $2} END {for (c in a) print c" "a[c]}' | sort -n | cut -d' ' -f2)
for k in 1 2 4 8; do
  for i in $(seq 0 $((k-1))); do
    timed taskset -c "${cores[$i]}" "$T" render examples/resolution.toml --width 1920 --height 1080 --samples 16 --threads 2 -o /tmp/pin-$i.png > /tmp/pin-$i.t &
  done
  wait
  echo "K=$k: $(cat $(seq -f /tmp/pin-%g.t 0 $((k-1))) | tr '\n' ' ')"
done
} >> "$OUTD/ceiling.txt" 2>&1
fi
if has pairs; then
{
echo "== pairs: one-thread render on CPU 0, alone and beside one on CPU j (800x600 4 spp)"
one() { timed taskset -c "$1" "$T" render examples/resolution.toml --threads 1 -o /tmp/pair-$1.png; }
echo "alone: $(one 0) s"
for j in $(seq 1 $(( $(nproc) - 1 ))); do
  one "$j" > /tmp/pair-other.t & o=$!
  a=$(one 0); wait $o
  echo "with CPU $j: $a s (CPU $j: $(cat /tmp/pair-other.t) s)"
done
} >> "$OUTD/ceiling.txt" 2>&1
fi
if has split; then
{
echo "== split: K concurrent 2-thread renders of 1920x1080 at 64/K spp (the K-worker farm's work, no farm; K=1 is bench-farm.sh's local render)"
for k in ${SPLIT_KS:-2 4 8}; do
  s=$EPOCHREALTIME
  for i in $(seq 1 "$k"); do
    timed "$T" render examples/resolution.toml --width 1920 --height 1080 --samples $((64 / k)) --threads 2 -o /tmp/split-$i.png > /tmp/split-$i.t &
  done
  wait
  echo "K=$k: all done in $(awk -v s="$s" -v e="$EPOCHREALTIME" 'BEGIN { printf "%.3f", e - s }') s; each: $(cat $(seq -f /tmp/split-%g.t 1 "$k") | tr '\n' ' ')"
done
} >> "$OUTD/split.txt" 2>&1
fi
if has farm; then
TESSERA_BIN=$T RESULT_LOAD_BIN=/bin/true OUT=/tmp/probe-farm LOAD_SECONDS=0 COUNTS="${COUNTS:-1 8}" \
  timeout "${FARM_TIMEOUT:-200}" scripts/bench-farm.sh 8 2 > "$OUTD/farm.txt" 2>&1
tar czf "$OUTD/farm-logs.tar.gz" -C /tmp/probe-farm $(cd /tmp/probe-farm && ls *.log)
fi
