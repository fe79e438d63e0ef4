#!/usr/bin/env bash
# Diagnostics for the farm's scaling on a many-core machine (device run):
# CPU topology, the machine's own scaling ceiling (K independent local
# renders, unpinned and pinned one render per physical core), and farm runs
# whose worker logs are kept for a timeline analysis (scripts/farm-timeline.py).
#   scripts/farm-probe.sh OUTDIR
set -uo pipefail
cd "$(dirname "$0")/.."
OUTD=${1:?outdir}; mkdir -p "$OUTD"
T=${TESSERA:-$PWD/.gpu/tessera}
{
echo "== topology"; nproc; lscpu; lscpu -e
echo "== ceiling, unpinned"
TESSERA=$T scripts/machine-ceiling.sh 2 1 2 4 8
} > "$OUTD/ceiling.txt" 2>&1
# Pinned: render k on the logical CPUs of core k as the guest sees them.
{
echo "== ceiling, pinned: one 2-thread render per guest core"
mapfile -t cores < <(lscpu -p=CORE,CPU | grep -v '^#' | sort -t, -k1,1n -k2,2n | awk -F, '{a[$1]=a[$1] (a[$1]==""?"":",") $2} END {for (c in a) print c" "a[c]}' | sort -n | cut -d' ' -f2)
printf '%s\n' "${cores[@]}"
for k in 1 2 4 8; do
  for i in $(seq 0 $((k-1))); do
    ( s=$EPOCHREALTIME; taskset -c "${cores[$i]}" "$T" render examples/resolution.toml --width 1920 --height 1080 --samples 16 --threads 2 -o /tmp/pin-$i.png >/dev/null 2>&1; awk -v s="$s" -v e="$EPOCHREALTIME" 'BEGIN { printf "%.3f\n", e - s }' > /tmp/pin-$i.t ) &
  done
  wait
  echo "K=$k: $(cat $(seq -f /tmp/pin-%g.t 0 $((k-1))) | tr '\n' ' ')"
done
} >> "$OUTD/ceiling.txt" 2>&1
# Which logical CPUs share a physical core on the host? The guest may see
# 16 "cores" that are 8 host cores with two hyper-threads each: a
# one-thread render on CPU 0 slows down when CPU j is a sibling.
{
echo "== pairs: one-thread render on CPU 0, alone and beside one on CPU j (800x600 4 spp)"
one() { local s=$EPOCHREALTIME; taskset -c "$1" "$T" render examples/resolution.toml --threads 1 -o /tmp/pair-$1.png >/dev/null 2>&1; awk -v s="$s" -v e="$EPOCHREALTIME" 'BEGIN { printf "%.3f", e - s }'; }
echo "alone: $(one 0) s"
for j in $(seq 1 $(( $(nproc) - 1 ))); do
  one "$j" > /tmp/pair-other.t & o=$!
  echo "with CPU $j: $(one 0) s (CPU $j: $(wait $o; cat /tmp/pair-other.t) s)"
done
} >> "$OUTD/ceiling.txt" 2>&1
# Farm runs at 64 spp with the workers' logs kept for scripts/farm-timeline.py.
TESSERA_BIN=$T RESULT_LOAD_BIN=/bin/true OUT=/tmp/probe-farm LOAD_SECONDS=0 COUNTS="${COUNTS:-1 8}" \
  timeout "${FARM_TIMEOUT:-200}" scripts/bench-farm.sh 8 2 > "$OUTD/farm.txt" 2>&1
tar czf "$OUTD/farm-logs.tar.gz" -C /tmp/probe-farm $(cd /tmp/probe-farm && ls *.log)
