#!/usr/bin/env bash
# Figures of scenes travelling with their files (issue 13), on this machine:
# - the dragon (shared/meshes/dragon_vrip.ply.gz) submitted twice over TLS
#   with tokens: the first submit uploads it, the second uploads nothing;
# - a worker's first fetch of it (from the worker's log);
# - a mesh job on three workers, each in a network namespace of its own,
#   against the same three workers on loopback.
# Usage: scripts/asset-figures.sh [TESSERA_BINARY]   (root, for namespaces)
set -euo pipefail
T=$(realpath "${1:-target/release/tessera}")
repo=$(cd "$(dirname "$0")/.." && pwd)
dragon=$repo/../shared/meshes/dragon_vrip.ply.gz
w=$(mktemp -d)
cleanup() {
  kill $(jobs -p) 2>/dev/null || true; sleep 0.5
  for n in tsfigsw tsfigh1 tsfigh2 tsfigh3 tsfigh4; do ip netns del $n 2>/dev/null || true; done
  ip link del tsfigt 2>/dev/null || true
  rm -rf "$w"
}
trap cleanup EXIT
cd "$w"
$T cert --out tls --tokens --name 127.0.0.1 --name 10.214.0.1 >/dev/null 2>&1
mkdir -p client
cp "$dragon" client/dragon.ply.gz
cat > client/dragon.toml <<'TOML'
[render]
width = 320
height = 240
samples = 4
[camera]
position = [0.0, 0.15, 0.35]
look_at = [0.0, 0.12, 0.0]
fov_y = 40.0
[materials.jade]
diffuse = [0.3, 0.7, 0.4]
specular = [0.3, 0.3, 0.3]
shininess = 30.0
[[lights]]
position = [1.0, 2.0, 2.0]
[[objects]]
type = "mesh"
path = "dragon.ply.gz"
material = "jade"
TOML
secure=(--tls-cert tls/coordinator.pem --tls-key tls/coordinator.key --client-token-file tls/client.token --worker-token-file tls/worker.token)
now() { date +%s.%N; }
wait_addr() { for _ in $(seq 100); do grep -q "listening on" "$1" 2>/dev/null && break; sleep 0.1; done; sed -n 's/listening on //p' "$1"; }

# 1. Upload, then re-submit, then a worker's first fetch.
$T coordinator --listen 127.0.0.1:0 --data data "${secure[@]}" >c.out 2>c.log &
addr=$(wait_addr c.out)
cl=(--coordinator "https://$addr" --ca tls/ca.pem --token-file tls/client.token)
t0=$(now); $T submit client/dragon.toml "${cl[@]}" 2>up1.txt >job1; t1=$(now)
$T submit client/dragon.toml "${cl[@]}" 2>up2.txt >job2; t2=$(now)
echo "first submit (parse + hash + upload of $(stat -c %s "$dragon") bytes): $(echo "$t1 - $t0" | bc) s; $(cat up1.txt)"
echo "second submit (parse + hash, nothing uploaded): $(echo "$t2 - $t1" | bc) s; $(cat up2.txt)"
$T worker --coordinator "https://$addr" --ca tls/ca.pem --token-file tls/worker.token --cache cache --threads 2 >/dev/null 2>w.log &
for _ in $(seq 600); do $T status "$(cat job2)" "${cl[@]}" 2>/dev/null | grep -q "state: *done" && break; sleep 0.2; done
grep "asset fetched" w.log | sed 's/.*bytes=\([0-9]*\) seconds=\([0-9.]*\).*/worker first fetch: \1 bytes in \2 s/' | sort -t: -k2 -n | tail -1
kill %1 %2 2>/dev/null || true; wait 2>/dev/null || true

# 2. One mesh job, three workers: loopback, then one namespace per host.
job() { # $1: coordinator url, prints seconds from submit to done
  local s e; s=$(now)
  $T submit client/dragon.toml --coordinator "$1" --ca tls/ca.pem --token-file tls/client.token --samples 16 --wait >/dev/null 2>&1
  e=$(now); echo "$e - $s" | bc
}
rm -rf data cache*
$T coordinator --listen 127.0.0.1:0 --data data "${secure[@]}" >c2.out 2>c2.log &
addr=$(wait_addr c2.out)
for i in 1 2 3; do $T worker --coordinator "https://$addr" --ca tls/ca.pem --token-file tls/worker.token --cache cache$i --threads 1 >/dev/null 2>&1 & done
sleep 1; job "https://$addr" >/dev/null # warm: each worker fetches and parses the dragon once
echo "mesh job, 3 workers on loopback (3 runs): $(job "https://$addr") $(job "https://$addr") $(job "https://$addr") s"
kill $(jobs -p) 2>/dev/null || true; wait 2>/dev/null || true

ip netns add tsfigsw; ip -n tsfigsw link add br0 type bridge; ip -n tsfigsw link set br0 up
for i in 1 2 3 4; do
  ip netns add tsfigh$i
  ip link add tsfigp$i netns tsfigsw type veth peer name eth0 netns tsfigh$i
  ip -n tsfigsw link set tsfigp$i master br0 up
  ip -n tsfigh$i addr add 10.214.0.$i/24 dev eth0; ip -n tsfigh$i link set eth0 up; ip -n tsfigh$i link set lo up
done
ip link add tsfigt type veth peer name tsfigp9 netns tsfigsw
ip -n tsfigsw link set tsfigp9 master br0 up; ip addr add 10.214.0.100/24 dev tsfigt; ip link set tsfigt up
rm -rf data cache*
ip netns exec tsfigh1 $T coordinator --listen 10.214.0.1:7878 --data data "${secure[@]}" >c3.out 2>c3.log &
wait_addr c3.out >/dev/null
for i in 2 3 4; do ip netns exec tsfigh$i $T worker --coordinator https://10.214.0.1:7878 --ca tls/ca.pem --token-file tls/worker.token --cache cache$i --threads 1 >/dev/null 2>&1 & done
sleep 1; job https://10.214.0.1:7878 >/dev/null
echo "mesh job, 3 workers in namespaces (3 runs): $(job https://10.214.0.1:7878) $(job https://10.214.0.1:7878) $(job https://10.214.0.1:7878) s"
kill $(jobs -p) 2>/dev/null || true; wait 2>/dev/null || true
ip link del tsfigt 2>/dev/null || true
