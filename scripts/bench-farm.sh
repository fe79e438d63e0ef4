#!/usr/bin/env bash
# Farm benchmark on this machine over loopback: the scaling of one frame
# over 1..N CPU workers (`tessera bench farm`, which checks every fetched
# frame against a local render bit for bit and writes CSV and plots), then
# the coordinator's result throughput under a load generator
# (coordinator/examples/result_load.rs).
#
#   scripts/bench-farm.sh [MAX_WORKERS] [THREADS_PER_WORKER]
#   env: LOAD_CLIENTS (64) LOAD_SECONDS (10) OUT (bench-out/farm)
#
# Worker counts are 1, 2, 4, ... up to MAX_WORKERS (and MAX_WORKERS itself).
# Linux only (/proc, for the coordinator's CPU time under load).
set -euo pipefail
cd "$(dirname "$0")/.."

MAX=${1:-8}
THREADS=${2:-2}
LOAD_CLIENTS=${LOAD_CLIENTS:-64}
LOAD_SECONDS=${LOAD_SECONDS:-10}

# TESSERA_BIN / RESULT_LOAD_BIN: prebuilt binaries (machines without cargo).
if [ -z "${TESSERA_BIN:-}" ]; then
    cargo build --release --quiet --bin tessera
    cargo build --release --quiet -p tessera-coordinator --example result_load
fi
T=${TESSERA_BIN:-$PWD/target/release/tessera}
LOAD=${RESULT_LOAD_BIN:-$PWD/target/release/examples/result_load}
# Arithmetic with awk: bc is not on every machine.
calc() { awk "BEGIN { print $* }"; }
OUT=${OUT:-bench-out/farm}
mkdir -p "$OUT"
TICK=$(getconf CLK_TCK)

pids=()
cleanup() { for p in "${pids[@]:-}"; do kill -9 "$p" 2>/dev/null || true; done; pids=(); }
trap cleanup EXIT

cpu_seconds() { awk -v t="$TICK" '{ printf "%.2f", ($14 + $15) / t }' "/proc/$1/stat"; }

counts=""; n=1
while [ "$n" -lt "$MAX" ]; do counts="$counts$n,"; n=$((n * 2)); done
counts="$counts$MAX"

echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs)"
"$T" bench farm --workers "$counts" --worker-threads "$THREADS" --out "$OUT"

echo
data="$OUT/data-load"
rm -rf "$data"
"$T" coordinator --listen 127.0.0.1:0 --data "$data" >"$data.addr" 2>"$data.log" &
COORD=$!
pids+=("$COORD")
for _ in $(seq 100); do grep -q 'listening on' "$data.addr" 2>/dev/null && break; sleep 0.05; done
URL="http://$(sed -n 's/listening on //p' "$data.addr")"
cpu0=$(cpu_seconds "$COORD")
"$LOAD" "$URL" examples/resolution.toml "$LOAD_CLIENTS" "$LOAD_SECONDS"
echo "coordinator CPU during the load: $(calc "$(cpu_seconds "$COORD") - $cpu0") s over ${LOAD_SECONDS} s"
