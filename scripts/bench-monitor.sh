#!/usr/bin/env bash
# What the web monitor costs the coordinator's result throughput: the
# result-throughput load test (coordinator/examples/result_load.rs: CLIENTS
# clients returning 8x8 results in batches of BATCH) against a coordinator
# serving --http, with no viewer and with VIEWERS monitor viewers, ROUNDS
# times alternately, in ABBA order (so drift in the machine's load and the
# order of the runs hit both alike). Each
# run gets a fresh coordinator: one coordinator slows down run after run
# (each run leaves a cancelled 3.2-million-unit job and up to 100,000
# remembered leases behind), which would count against whichever condition
# runs later.
#
#   scripts/bench-monitor.sh [ROUNDS] [VIEWERS]
#   env: LOAD_CLIENTS (64) LOAD_SECONDS (10) BATCH (64)
#        TESSERA_BIN, RESULT_LOAD_BIN: prebuilt binaries (default: release builds)
#
# Prints each run's line with the coordinator's CPU time (user + system,
# from /proc), then the median of each condition, the cost in percent of
# results/s and of coordinator CPU per result (which moves less with other
# load on the machine), and the monitor's own counters (GET /api/monitor)
# of the last run with viewers. Linux only (/proc).
set -euo pipefail
cd "$(dirname "$0")/.."

ROUNDS=${1:-3}
VIEWERS=${2:-10}
LOAD_CLIENTS=${LOAD_CLIENTS:-64}
LOAD_SECONDS=${LOAD_SECONDS:-10}
BATCH=${BATCH:-64}

if [ -z "${TESSERA_BIN:-}" ]; then
    cargo build --release --quiet --bin tessera
    cargo build --release --quiet -p tessera-coordinator --example result_load
fi
T=${TESSERA_BIN:-$PWD/target/release/tessera}
LOAD=${RESULT_LOAD_BIN:-$PWD/target/release/examples/result_load}
OUT=${OUT:-bench-out/monitor}
mkdir -p "$OUT"
TICK=$(getconf CLK_TCK)

COORD=
trap 'if [ -n "$COORD" ]; then kill -9 "$COORD" 2>/dev/null || true; fi' EXIT
start_coordinator() {
    rm -rf "$OUT/data" "$OUT/addr"
    "$T" coordinator --listen 127.0.0.1:0 --http 127.0.0.1:0 --data "$OUT/data" >"$OUT/addr" 2>"$OUT/coordinator.log" &
    COORD=$!
    for _ in $(seq 200); do grep -q 'monitor on' "$OUT/addr" 2>/dev/null && break; sleep 0.05; done
    URL="http://$(sed -n 's/listening on //p' "$OUT/addr")"
    MON=$(sed -n 's/monitor on //p' "$OUT/addr")
}
stop_coordinator() { kill "$COORD" 2>/dev/null || true; wait "$COORD" 2>/dev/null || true; COORD=; }
cpu() { awk -v t="$TICK" '{ printf "%.3f", ($14 + $15) / t }' "/proc/$COORD/stat"; }
median() { printf '%s\n' "$@" | sort -n | awk '{ a[NR] = $1 } END { print (NR % 2) ? a[(NR + 1) / 2] : (a[NR / 2] + a[NR / 2 + 1]) / 2 }'; }

echo "machine: $(nproc) CPUs, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //'); load average $(cut -d' ' -f1-3 /proc/loadavg)"
echo "$LOAD_CLIENTS clients, batches of $BATCH, $LOAD_SECONDS s a run, a fresh coordinator each"
none=(); viewed=(); none_cpu=(); viewed_cpu=(); counters=
for r in $(seq "$ROUNDS"); do
    # ABBA: which condition runs first alternates, so an advantage of
    # running first or second (seen here: up to 10%) cancels out.
    order=(0 "$VIEWERS"); if [ $((r % 2)) = 0 ]; then order=("$VIEWERS" 0); fi
    for v in "${order[@]}"; do
        start_coordinator
        c0=$(cpu)
        if [ "$v" = 0 ]; then
            line=$("$LOAD" "$URL" examples/resolution.toml "$LOAD_CLIENTS" "$LOAD_SECONDS" "$BATCH")
        else
            line=$("$LOAD" "$URL" examples/resolution.toml "$LOAD_CLIENTS" "$LOAD_SECONDS" "$BATCH" "$v" "$MON")
            counters=$(curl -s "$MON/api/monitor" 2>/dev/null || echo unavailable)
        fi
        c1=$(cpu)
        stop_coordinator
        rate=$(echo "$line" | sed -n 's/.*= \([0-9]*\) results\/s.*/\1/p' | head -1)
        n=$(echo "$line" | sed -n 's/.*results accepted \([0-9]*\) .*/\1/p' | head -1)
        # Coordinator CPU microseconds per accepted result (the submit's cost probe included).
        us=$(awk -v a="$c0" -v b="$c1" -v n="$n" 'BEGIN { printf "%.1f", 1e6 * (b - a) / n }')
        echo "round $r, $v viewers: $(echo "$line" | tr '\n' ' ') coordinator CPU $(awk -v a="$c0" -v b="$c1" 'BEGIN { printf "%.2f", b - a }') s, $us us/result"
        if [ "$v" = 0 ]; then none+=("$rate"); none_cpu+=("$us"); else viewed+=("$rate"); viewed_cpu+=("$us"); fi
    done
done
m0=$(median "${none[@]}"); m1=$(median "${viewed[@]}")
echo "median results/s: no viewer $m0 (${none[*]}), $VIEWERS viewers $m1 (${viewed[*]})"
awk -v a="$m0" -v b="$m1" 'BEGIN { printf "monitor cost: %.1f%% of the result throughput (medians)\n", 100 * (a - b) / a }'
# Each round's two runs are neighbours in time: their ratio cancels most
# drift in the machine's other load.
ratios=(); for i in "${!none[@]}"; do ratios+=("$(awk -v a="${none[$i]}" -v b="${viewed[$i]}" 'BEGIN { printf "%.4f", b / a }')"); done
mr=$(median "${ratios[@]}")
echo "per round, results/s with viewers over without: ${ratios[*]}"
awk -v r="$mr" 'BEGIN { printf "monitor cost: %.1f%% of the result throughput (median of the rounds)\n", 100 * (1 - r) }'
u0=$(median "${none_cpu[@]}"); u1=$(median "${viewed_cpu[@]}")
echo "median coordinator CPU per result: no viewer $u0 us (${none_cpu[*]}), $VIEWERS viewers $u1 us (${viewed_cpu[*]})"
awk -v a="$u0" -v b="$u1" 'BEGIN { printf "monitor cost: %.1f%% more coordinator CPU per result\n", 100 * (b - a) / a }'
echo "monitor counters (the last run with viewers): $counters"
