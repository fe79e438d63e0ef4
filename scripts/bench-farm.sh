#!/usr/bin/env bash
# Farm scaling benchmark: one frame rendered by 1..N CPU workers on this
# machine over loopback, plus the coordinator's result throughput.
#
#   scripts/bench-farm.sh [MAX_WORKERS] [THREADS_PER_WORKER]
#   env: SCENE (examples/resolution.toml) WIDTH (1920) HEIGHT (1080) SAMPLES (64)
#        LOAD_CLIENTS (64) LOAD_SECONDS (10) COUNTS (worker counts; default 1..MAX_WORKERS)
#        LOAD_SECONDS=0 skips the result-throughput load; TILE (tile size; default the coordinator's)
#
# For each worker count it reports wall time of the job (submit to done),
# speed-up and parallel efficiency relative to 1 worker, the coordinator's
# own CPU time (user+system, from /proc), the bytes each worker wrote per
# work unit (results on the wire, from /proc/PID/io wchar), how busy the
# workers' renderers were (sum of the units' render times, from the
# workers' JSON debug logs, over workers x wall time: the rest is waiting
# on the network, start-up and the job's tail; scripts/farm-timeline.py
# breaks it down per worker from the same logs), and finally the
# result messages per second the coordinator accepts from the load generator
# (coordinator/examples/result_load.rs). Linux only (/proc).
set -euo pipefail
cd "$(dirname "$0")/.."

MAX=${1:-8}
THREADS=${2:-2}
SCENE=${SCENE:-examples/resolution.toml}
WIDTH=${WIDTH:-1920}
HEIGHT=${HEIGHT:-1080}
SAMPLES=${SAMPLES:-64}
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
wchar() { awk '/^wchar/ { print $2 }' "/proc/$1/io"; }

start_coordinator() {
    local data=$1
    rm -rf "$data"
    "$T" coordinator --listen 127.0.0.1:0 --data "$data" >"$data.addr" 2>"$data.log" &
    COORD=$!
    pids+=("$COORD")
    for _ in $(seq 100); do grep -q 'listening on' "$data.addr" 2>/dev/null && break; sleep 0.05; done
    URL="http://$(sed -n 's/listening on //p' "$data.addr")"
}

echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs)"
echo "scene: $SCENE ${WIDTH}x${HEIGHT} ${SAMPLES} spp; workers of $THREADS threads"
start=$(date +%s.%N)
"$T" render "$SCENE" --width "$WIDTH" --height "$HEIGHT" --samples "$SAMPLES" --threads "$THREADS" -o "$OUT/local.png" | tail -1
echo "local render (tessera render --threads $THREADS): $(calc "$(date +%s.%N) - $start") s"
echo
printf "%8s %10s %9s %11s %14s %8s %15s %12s\n" workers seconds speedup efficiency coordinator_cpu units bytes_per_unit render_busy
base=""
for n in ${COUNTS:-$(seq 1 "$MAX")}; do
    start_coordinator "$OUT/data-$n"
    wpids=()
    for i in $(seq "$n"); do
        RUST_LOG=info,tessera_worker=debug "$T" worker --coordinator "$URL" --threads "$THREADS" --name "bench-$i" \
            --log-format json 2>>"$OUT/data-$n.worker-$i.log" &
        wpids+=("$!"); pids+=("$!")
    done
    for _ in $(seq 200); do
        [ "$("$T" workers --coordinator "$URL" | tail -n +2 | wc -l)" -ge "$n" ] && break; sleep 0.05
    done
    t0=$(date +%s.%N)
    id=$("$T" submit "$SCENE" --coordinator "$URL" --width "$WIDTH" --height "$HEIGHT" --samples "$SAMPLES" ${TILE:+--tile-size "$TILE"} --wait)
    t1=$(date +%s.%N)
    secs=$(calc "$t1 - $t0")
    cpu=$(cpu_seconds "$COORD")
    units=$("$T" status "$id" --coordinator "$URL" | sed -n 's/.*(\([0-9]*\) of [0-9]* units).*/\1/p')
    bytes=0; for p in "${wpids[@]}"; do bytes=$((bytes + $(wchar "$p"))); done
    [ -z "$base" ] && base=$secs
    render=$(sed -n 's/.*"message":"unit rendered".*"seconds":\([0-9.e-]*\).*/\1/p' "$OUT"/data-$n.worker-*.log | awk '{ s += $1 } END { print s + 0 }')
    printf "%8d %10.2f %9.2f %10.1f%% %13ss %8d %15d %11.1f%%\n" "$n" "$secs" "$(calc "$base / $secs")" \
        "$(calc "100 * $base / $secs / $n")" "$cpu" "$units" "$((bytes / units))" "$(calc "100 * $render / $secs / $n")"
    "$T" fetch "$id" --coordinator "$URL" -o "$OUT/frames-$n" 2>/dev/null
    cmp -s "$OUT/frames-$n/frame_0000.png" "$OUT/local.png" || echo "   WARNING: image differs from tessera render"
    cleanup
done

[ "$LOAD_SECONDS" = 0 ] && exit 0
echo
start_coordinator "$OUT/data-load"
cpu0=$(cpu_seconds "$COORD")
"$LOAD" "$URL" "$SCENE" "$LOAD_CLIENTS" "$LOAD_SECONDS"
echo "coordinator CPU during the load: $(calc "$(cpu_seconds "$COORD") - $cpu0") s over ${LOAD_SECONDS} s"
