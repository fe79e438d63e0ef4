#!/usr/bin/env bash
# What the web monitor costs the coordinator's result throughput: the
# result-throughput load test (coordinator/examples/result_load.rs: CLIENTS
# clients returning 8x8 results in batches of BATCH) against one coordinator
# serving --http, with no viewer and with VIEWERS monitor viewers, ROUNDS
# times alternately (so drift in the machine's load hits both alike).
#
#   scripts/bench-monitor.sh [ROUNDS] [VIEWERS]
#   env: LOAD_CLIENTS (64) LOAD_SECONDS (10) BATCH (64)
#        TESSERA_BIN, RESULT_LOAD_BIN: prebuilt binaries (default: release builds)
#
# Prints each run's line, then the median of each condition, the cost in
# percent, and the monitor's own counters (GET /api/monitor).
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
data=$OUT/data
rm -rf "$data"

"$T" coordinator --listen 127.0.0.1:0 --http 127.0.0.1:0 --data "$data" >"$OUT/addr" 2>"$OUT/coordinator.log" &
COORD=$!
trap 'kill -9 $COORD 2>/dev/null || true' EXIT
for _ in $(seq 200); do grep -q 'monitor on' "$OUT/addr" 2>/dev/null && break; sleep 0.05; done
URL="http://$(sed -n 's/listening on //p' "$OUT/addr")"
MON=$(sed -n 's/monitor on //p' "$OUT/addr")

echo "machine: $(nproc) CPUs, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //'); load average $(cut -d' ' -f1-3 /proc/loadavg)"
echo "coordinator $URL, monitor $MON; $LOAD_CLIENTS clients, batches of $BATCH, $LOAD_SECONDS s a run"
none=(); viewed=()
for r in $(seq "$ROUNDS"); do
    for v in 0 "$VIEWERS"; do
        if [ "$v" = 0 ]; then
            line=$("$LOAD" "$URL" examples/resolution.toml "$LOAD_CLIENTS" "$LOAD_SECONDS" "$BATCH")
        else
            line=$("$LOAD" "$URL" examples/resolution.toml "$LOAD_CLIENTS" "$LOAD_SECONDS" "$BATCH" "$v" "$MON")
        fi
        rate=$(echo "$line" | sed -n 's/.*= \([0-9]*\) results\/s.*/\1/p' | head -1)
        echo "round $r, $v viewers: $(echo "$line" | tr '\n' ' ')"
        if [ "$v" = 0 ]; then none+=("$rate"); else viewed+=("$rate"); fi
    done
done
median() { printf '%s\n' "$@" | sort -n | awk '{ a[NR] = $1 } END { print (NR % 2) ? a[(NR + 1) / 2] : (a[NR / 2] + a[NR / 2 + 1]) / 2 }'; }
m0=$(median "${none[@]}"); m1=$(median "${viewed[@]}")
echo "median results/s: no viewer $m0 (${none[*]}), $VIEWERS viewers $m1 (${viewed[*]})"
awk -v a="$m0" -v b="$m1" 'BEGIN { printf "monitor cost: %.1f%% of the result throughput\n", 100 * (a - b) / a }'
echo "monitor counters: $(curl -s "$MON/api/monitor" 2>/dev/null || echo unavailable)"
