#!/usr/bin/env bash
# The benchmark run on the NVIDIA benchmark machine (see ../shared/GPU.md):
# prebuilt binaries in .gpu/ (tessera, result_load, libvulkan.so.1), no cargo.
# Writes everything under $OUT (or bench-out/device). $TESSERA_BIN names
# another binary of .gpu/ to run (e.g. tessera-base, a before/after).
#
#   scripts/device-bench.sh [PHASE...]     phases: bench depth farm (default: all three), adaptive, farm-image, local-gpu,
#                                          gpu-tests, against-old, meshes-against-old, cpu-worker, farm-gpu, multi-gpu,
#                                          path, launch-path, path-bench, assets, environment, instancing, big-mesh,
#                                          scale, image-rounds, uniform
#
# `cpu-worker` (issue 15, ~2 min): the 1-worker pairs of `bench farm
# --repeat 5` between whole `tessera render --threads 2` processes, to tell
# the farm's cost from a process's. `farm-gpu` (~1 min): the GPU worker
# alone and beside 7 CPU workers with the coordinator's and workers' debug
# logs, their timelines and the store writer's busy time per job
# (scripts/writer-busy.py).
#
# At most 8 files come back from a device call's $OUT: a call that runs
# two phases (each `adaptive` run leaves 7 and a tarball) must keep only
# what it needs (headline, summary, csv, corona) or pack them.
#
# `adaptive` (issue 17; not in the default) runs `tessera bench adaptive`
# on the scenes in $ADAPTIVE_SCENES (default distributed; one scene a
# device call: $ADAPTIVE_SIZE, default 400x300, with an f64 reference of
# $ADAPTIVE_REFERENCE spp, default 4096), uniform and adaptive on
# $ADAPTIVE_BACKEND (default both); $ADAPTIVE_ARGS goes to the command
# (`--integrator path`: the path-traced case).
#
# `image-rounds` (issue 36; not in the default; ~4 min): the error-optimal
# mode's CPU rounds against uniform sampling, one `tessera render` at a
# time on all cores, for each binary in $IMAGE_ROUNDS_BINS (default
# "tessera"; e.g. "tessera tessera-base" for a before/after, interleaved,
# twice each): per case in $IMAGE_ROUNDS_CASES ("scene:target[:args]";
# default the H200 tables' distributed and quad scenes, Whitted and path,
# at uniform 1024 spp's RMSE) uniform 1024 spp and `--adaptive-mode image`
# at that target, 16..4096 spp, $IMAGE_ROUNDS_SIZE (default 320x240).
#
# `local-gpu` (issue 15; ~2 min): a fresh process's small GPU render with
# the pipeline cache off, empty and warm, against the CPU and against a
# process that only opens the GPU (`tessera gpus`); then `tessera bench
# launch` (1080p 4 spp: sums read back against the image resolved on the
# GPU, and the launch sweep).
#
# `gpu-tests` runs tracer-core's GPU test binary (.gpu/gpu-tests, built by
# `cargo test -p tracer-core --test gpu --no-run`) on the NVIDIA GPU: every
# GPU path (moving meshes, distributed effects, the GPU resolve) against the
# CPU reference on real hardware, not only lavapipe.
#
# `path` (issue 35; not in the default; ~1 min): `--integrator path` on
# cornell.toml and distributed.toml at 1920x1080 64 spp, CPU (all cores) and
# GPU, twice each (the summary line's Mpaths/s and Mrays/s; the first GPU
# run builds the pipeline), then tracer-core's GPU path tests
# (.gpu/gpu-path-tests, built by `cargo test -p tracer-core --test gpu_path
# --no-run`) on the NVIDIA GPU: CPU against GPU images on real hardware.
#
# `launch-path` (issue 35; not in the default; ~3 min): `tessera bench
# launch --integrator path --backend gpu`: the stack and wavefront path
# drivers over launch shapes (launch-path-*.txt, launch-path.csv).
#
# `uniform` (~3 min with two binaries): uniform CPU renders on all cores,
# before/after across $UNIFORM_BINS (see the phase for its variables).
#
# `path-bench` (issue 35; not in the default; ~3 min): `tessera bench path
# --backend both` with Mitsuba 3's cuda_ad_rgb (from .gpu/mitsuba.tar.xz,
# made by scripts/device-mitsuba.sh) at $PATH_SIZE (default 512x512),
# samples $PATH_SAMPLES (default 1,4,16,64,256), f64 reference of
# $PATH_REFERENCE spp (default 1024).
#
# `assets` (issues 34 and 35; not in the default; ~3 min): every model file
# under .gpu/scenes (a copy of ../shared/scenes: ../shared does not travel)
# rendered as a user would, `tessera render FILE --json` at 800x600, Whitted
# 16 spp and path 64 spp, on the CPU (all cores) and the GPU, one process
# each (a GPU render twice, cold and warm pipelines; $ASSET_BACKENDS,
# default "cpu gpu"): triangles, textures, load, build and render seconds
# and peak RSS into assets.jsonl; the path pictures come back as
# assets/*.png.
#
# `environment` (issue 35; not in the default; ~2 min): DamagedHelmet
# path-traced at 1920x1080 64 spp under its default sky and under
# .gpu/sky.exr (scripts/sky-exr.py: 512x256, a sun), on the CPU (all
# cores) and the GPU (twice: cold and warm pipelines), `--json` lines into
# environment.jsonl: what importance-sampling an image costs; the GPU's
# picture comes back.
#
# `instancing` (issue 34; not in the default; ~2 min): one torus placed
# by 1 to 1,000 nodes, instanced and copied, CPU and GPU (`--json`: peak
# RSS, gpu_scene_bytes, seconds) into instancing.jsonl.
#
# `scale` (issue 38; not in the default; ~2 min): `tessera bench scale
# --virtual-workers 2000` with units of 0 and 200 ms on this machine's
# cores.
#
# `against-old` (issue 16) times the thesis scenes with .gpu/tessera and an
# earlier build, .gpu/tessera-old, interleaved run by run (5 each), CPU and
# GPU, from the summary line's in-process seconds: a scene without the new
# effects must keep its speed. EXR output, so both builds read back the sums.
#
# `multi-gpu` (issue 21; not in the default; for a machine of several GPUs)
# runs `tessera bench multi-gpu` with one GPU worker per adapter `tessera
# gpus` lists (or per entry of $MULTI_GPU_ADAPTERS, e.g. 0,1,2,3; on a
# one-GPU box MULTI_GPU_ADAPTERS=0,0 runs two workers sharing the GPU), for
# 1..N of them, on a 1920x1080 256-spp frame and a 24-frame 1080p 64-spp
# animation, against N concurrent local GPU renders of 1/N of the work;
# then the same GPU workers beside CPU workers of 2 threads filling the
# other cores: (nproc - N - 1) / 2 of them beside N GPU workers (a core
# feeds each GPU worker, one is the coordinator's). Then the CPU workers
# alone, `tessera bench farm --workers 1,2,4,8,16 --worker-threads 2` (the
# counts whose threads fit in nproc). Writes multi-gpu-*.txt, multi-gpu.csv,
# cpu-farm.csv and the plots (in the tarball) under $OUT; ~5 min with 2
# GPU workers and 16 cores ($MULTI_GPU_TIMEOUT, $CPU_FARM_TIMEOUT cap each
# part). $MULTI_GPU_ARGS goes to both bench commands (--quick: a dry run).
#
# `bench` (every suite but depth and farm) fits one 10-minute device call;
# `depth` (the depth suite against its depth-32 reference, ~2 min of 16
# cores) and `farm` (the farm suite with GPU and mixed runs, latency and
# result throughput, ~4 min) fit another.
set -uo pipefail
PHASES=" ${*:-bench depth farm} "
has() { [[ "$PHASES" == *" $1 "* ]]; }
PHASE=$(echo ${PHASES} | tr ' ' '-')
cd "$(dirname "$0")/.."
OUT=$(realpath -m "${OUT:-bench-out/device}")
mkdir -p "$OUT"
printf '{"file_format_version":"1.0.0","ICD":{"library_path":"/usr/local/nvidia/lib64/libEGL_nvidia.so.0","api_version":"1.3"}}' > /tmp/icd.json
export VK_ICD_FILENAMES=/tmp/icd.json LD_LIBRARY_PATH=$PWD/.gpu:/usr/local/nvidia/lib64${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
# Binaries may travel xz-packed (the call's tree is capped at 64 MiB).
for x in .gpu/*.xz; do
  case $x in *.tar.xz) continue ;; esac
  [ -e "${x%.xz}" ] || { python3 -c 'import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.argv[1]), open(sys.argv[2], "wb"))' "$x" "${x%.xz}" && chmod +x "${x%.xz}"; }
done
T=$PWD/.gpu/${TESSERA_BIN:-tessera}
# The tests' shared assets: .gpu/scenes is a copy of ../shared/scenes.
[ -d .gpu/scenes ] && export TESSERA_SHARED=$PWD/.gpu
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
if has adaptive; then
echo "== tessera bench adaptive --backend ${ADAPTIVE_BACKEND:-both} (${ADAPTIVE_SCENES:-distributed})"
timeout "${ADAPTIVE_TIMEOUT:-560}" "$T" bench adaptive --backend "${ADAPTIVE_BACKEND:-both}" \
  --adaptive-scenes "${ADAPTIVE_SCENES:-distributed}" \
  --adaptive-size "${ADAPTIVE_SIZE:-400x300}" --adaptive-reference "${ADAPTIVE_REFERENCE:-4096}" ${ADAPTIVE_ARGS:-} \
  --out /tmp/bench --cache /tmp/bench-cache > "$OUT/adaptive-summary.txt" 2> "$OUT/adaptive-log.txt"
echo "adaptive exit $?" >> "$OUT/adaptive-summary.txt"
mkdir -p "$OUT/adaptive"
cp /tmp/bench/adaptive.csv /tmp/bench/adaptive/error_vs_time.* /tmp/bench/adaptive/headline.txt /tmp/bench/adaptive/corona.md "$OUT/adaptive/" 2>/dev/null
fi
if has local-gpu; then
ms() { local t0 t1; t0=$(date +%s%N); "$@" > /dev/null 2>&1; local rc=$?; t1=$(date +%s%N); echo "$(( (t1 - t0) / 1000000 )) ms (rc $rc)"; }
{
  echo "== machine"; nproc; nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
  small=(examples/resolution.toml --width 160 --height 120 --samples 4)
  for i in 1 2 3; do echo "cpu render 160x120 4 spp, whole process: $(ms "$T" render "${small[@]}" -o /tmp/s-cpu.png)"; done
  for i in 1 2 3; do echo "tessera gpus (open Vulkan, list adapters), whole process: $(ms "$T" gpus)"; done
  for i in 1 2 3; do echo "gpu render, pipeline cache off, whole process: $(TESSERA_PIPELINE_CACHE=off ms "$T" render "${small[@]}" --backend gpu -o /tmp/s-gpu-off.png)"; done
  rm -rf /tmp/pcache
  for i in 1 2 3; do echo "gpu render, pipeline cache (run $i; empty before run 1), whole process: $(TESSERA_PIPELINE_CACHE=/tmp/pcache ms "$T" render "${small[@]}" --backend gpu -o /tmp/s-gpu-cache.png)"; done
  ls -l /tmp/pcache
  cmp /tmp/s-gpu-off.png /tmp/s-gpu-cache.png && echo "cached and uncached images identical"
  echo "== the render call's own time (first call of a process: pipelines built), cache off, warm, and a 16x16 frame"
  TESSERA_PIPELINE_CACHE=off "$T" render "${small[@]}" --backend gpu -o /tmp/s-gpu-off.png --json
  TESSERA_PIPELINE_CACHE=/tmp/pcache "$T" render "${small[@]}" --backend gpu -o /tmp/s-gpu-cache.png --json
  TESSERA_PIPELINE_CACHE=/tmp/pcache "$T" render examples/resolution.toml --width 16 --height 16 --samples 1 --backend gpu -o /tmp/s-gpu-16.png --json
  "$T" render "${small[@]}" -o /tmp/s-cpu.png --json
  echo "== 1080p 64 spp, tessera render --backend gpu (image resolved on the GPU)"
  for i in 1 2; do TESSERA_PIPELINE_CACHE=/tmp/pcache "$T" render examples/resolution.toml --backend gpu --width 1920 --height 1080 --samples 64 -o /tmp/hd.png; done
} > "$OUT/local-gpu.txt" 2>&1
echo "== tessera bench launch (1080p 4 spp)"
timeout 300 "$T" bench launch --backend gpu --repeat 3 --out /tmp/bench --cache /tmp/bench-cache \
  > "$OUT/launch-summary.txt" 2> "$OUT/launch-log.txt"
echo "launch exit $?" >> "$OUT/launch-summary.txt"
fi
if has path; then
{
  echo "== machine"; nproc; nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
  for scene in cornell distributed; do
    for backend in cpu gpu gpu; do
      echo "== $scene, --integrator path, $backend"
      "$T" render "examples/$scene.toml" --integrator path --backend "$backend" \
        --width 1920 --height 1080 --samples 64 -o "/tmp/path-$scene-$backend.png"
    done
  done
} > "$OUT/path.txt" 2>&1
if [ -x .gpu/gpu-path-tests ]; then
  [ -e /work/main ] || { mkdir -p /work && ln -s "$PWD" /work/main; }
  CI=true TESSERA_TEST_ADAPTER=NVIDIA timeout 300 .gpu/gpu-path-tests --nocapture --test-threads 1 \
    > "$OUT/gpu-path-tests.txt" 2>&1
  echo "gpu path tests exit $?" >> "$OUT/gpu-path-tests.txt"
fi
fi
if has launch-path; then
# Issue 35's wavefront path driver against the stack driver: the launch
# sweep (1080p 4 spp, resolution and glass-9) with --integrator path.
timeout "${LAUNCH_PATH_TIMEOUT:-300}" "$T" bench launch --integrator path --backend gpu --repeat 3 \
  --out /tmp/bench-lp --cache /tmp/bench-cache > "$OUT/launch-path-summary.txt" 2> "$OUT/launch-path-log.txt"
echo "launch-path exit $?" >> "$OUT/launch-path-summary.txt"
cp /tmp/bench-lp/launch.csv "$OUT/launch-path.csv" 2>/dev/null
fi
if has image-rounds; then
size=${IMAGE_ROUNDS_SIZE:-320x240}
cases=${IMAGE_ROUNDS_CASES:-"distributed:1.126e-3 resolution-quad:4.949e-4 distributed:3.793e-4:--integrator=path resolution-quad:8.039e-4:--integrator=path"}
{
  echo "== machine"; nproc; grep -m1 'model name' /proc/cpuinfo
  for c in $cases; do
    IFS=: read -r scene target args <<< "$c"
    args=${args//=/ }
    for b in ${IMAGE_ROUNDS_BINS:-tessera}; do
      echo "== $scene $args $b uniform 1024 spp"
      .gpu/$b render "examples/$scene.toml" --width "${size%x*}" --height "${size#*x}" --samples 1024 \
        --sampler progressive $args -o /tmp/ir-u.png 2>&1 | grep -E 'cpu:'
    done
    for rep in 1 2; do
      for b in ${IMAGE_ROUNDS_BINS:-tessera}; do
        echo "== $scene $args $b image mode, target $target (run $rep)"
        .gpu/$b render "examples/$scene.toml" --width "${size%x*}" --height "${size#*x}" --target-error "$target" \
          --adaptive-mode image --min-samples 16 --max-samples 4096 $args -o "/tmp/ir-$b.png" 2>&1 | grep -E 'cpu:|^adaptive'
      done
    done
  done
} > "$OUT/image-rounds.txt" 2>&1
fi
if has uniform; then
# Uniform CPU renders on all cores, one process each, interleaved across
# the binaries of $UNIFORM_BINS (default "tessera"; "tessera tessera-base"
# for a before/after), $UNIFORM_REPEAT times (default 5): per case of
# $UNIFORM_CASES ("scene:WxH:spp[:args]") the summary line.
cases=${UNIFORM_CASES:-"distributed:320x240:1024 resolution-quad:320x240:1024 resolution:320x240:1024 distributed:320x240:1024:--integrator=path distributed:640x480:256"}
{
  echo "== machine"; nproc; grep -m1 'model name' /proc/cpuinfo
  for c in $cases; do
    IFS=: read -r scene size spp args <<< "$c"
    args=${args//=/ }
    for rep in $(seq "${UNIFORM_REPEAT:-5}"); do
      for b in ${UNIFORM_BINS:-tessera}; do
        echo "== $scene $size $spp spp $args $b (run $rep)"
        .gpu/$b render "examples/$scene.toml" --width "${size%x*}" --height "${size#*x}" --samples "$spp" \
          $args -o /tmp/uniform.png 2>&1 | grep -E 'cpu:|^path'
      done
    done
  done
} > "$OUT/uniform.txt" 2>&1
fi
if has path-bench; then
mkdir -p /tmp/mi && python3 -c 'import tarfile, sys; tarfile.open(sys.argv[1]).extractall(sys.argv[2])' .gpu/mitsuba.tar.xz /tmp/mi
{
  echo "== machine"; nproc; nvidia-smi --query-gpu=name,driver_version --format=csv,noheader; python3 --version
  PYTHONPATH=/tmp/mi python3 -c "import mitsuba as mi; mi.set_variant('cuda_ad_rgb'); print('mitsuba', mi.__version__, mi.variant())"
  echo "== tessera bench path --backend both, Mitsuba cuda_ad_rgb, ${PATH_SIZE:-512x512}, samples ${PATH_SAMPLES:-1,4,16,64,256}"
  PYTHONPATH=/tmp/mi TESSERA_MITSUBA_VARIANT=cuda_ad_rgb timeout "${PATH_TIMEOUT:-400}" "$T" bench path --backend both \
    --path-size "${PATH_SIZE:-512x512}" --path-samples "${PATH_SAMPLES:-1,4,16,64,256}" \
    --path-reference "${PATH_REFERENCE:-1024}" --out /tmp/bench --cache /tmp/bench-cache
  echo "path bench exit $?"
} > "$OUT/path-bench.txt" 2>&1
mkdir -p "$OUT/path-bench"
cp /tmp/bench/path/error_vs_time.* /tmp/bench/path.csv "$OUT/path-bench/" 2>/dev/null
fi
if has assets; then
mkdir -p "$OUT/assets"
# A GPU render's seconds include building its pipelines, once per scene
# variant and process: each GPU render runs twice with one pipeline cache
# ($TESSERA_PIPELINE_CACHE), "run" 1 (cold) and 2 (warm).
for f in $(find .gpu/scenes -name '*.gltf' -o -name '*.glb' -o -name '*.obj' -o -name '*.obj.gz' | sort); do
  name=$(basename "$f"); name=${name%%.*}
  for backend in ${ASSET_BACKENDS:-cpu gpu}; do
    for spec in "whitted 16" "path 64"; do
      set -- $spec
      runs=1; [ "$backend" = gpu ] && runs="1 2"
      for run in $runs; do
        line=$(TESSERA_PIPELINE_CACHE=/tmp/asset-pcache timeout 120 "$T" render "$f" --backend "$backend" --integrator "$1" --samples "$2" \
          --width 800 --height 600 -o "/tmp/asset-$name-$backend-$1.png" --json 2>"/tmp/asset-$name-$backend-$1.err")
        rc=$?
        python3 -c 'import json, sys; print(json.dumps({"file": sys.argv[1], "backend": sys.argv[2], "integrator": sys.argv[3], "run": int(sys.argv[7]), "exit": int(sys.argv[4]), "report": json.loads(sys.argv[5]) if sys.argv[5] else None, "stderr": open(sys.argv[6]).read()[-2000:]}))' \
          "$f" "$backend" "$1" "$rc" "$line" "/tmp/asset-$name-$backend-$1.err" "$run" >> "$OUT/assets.jsonl"
      done
      [ "$1" = path ] && cp "/tmp/asset-$name-$backend-$1.png" "$OUT/assets/" 2>/dev/null
    done
  done
done
fi
if has environment; then
H=.gpu/scenes/gltf/DamagedHelmet/glTF/DamagedHelmet.gltf
for env in sky image; do
  flag=(); [ "$env" = image ] && flag=(--environment .gpu/sky.exr)
  for b in cpu gpu gpu; do
    echo "{\"environment\": \"$env\", \"backend\": \"$b\", \"render\": $("$T" render "$H" --integrator path --width 1920 --height 1080 --samples 64 --backend $b "${flag[@]}" --json -o /tmp/env-$env-$b.png 2>/tmp/env.err || cat /tmp/env.err)}"
  done
done > "$OUT/environment.jsonl"
cp /tmp/env-image-gpu.png "$OUT/helmet-environment-gpu.png" 2>/dev/null
fi
if has instancing; then
# One 19,800-triangle torus placed by 1, 10, 100 and 1,000 nodes (and the
# same files with the mesh copied per node, up to 100), scripts/torus-grid.py:
# `tessera render --json` at 1920x1080 16 spp on the CPU (all cores) and the
# GPU (twice: cold and warm pipelines): peak RSS, the GPU's scene bytes,
# prepare and render seconds, one line each into instancing.jsonl.
for n in 1 10 100 1000; do
  for form in instanced copied; do
    [ "$form" = copied ] && [ "$n" -gt 100 ] && continue
    [ "$form" = copied ] && [ "$n" = 1 ] && continue
    python3 scripts/torus-grid.py "/tmp/grid-$n-$form.gltf" "$n" "$form"
    for b in cpu gpu gpu; do
      line=$(TESSERA_PIPELINE_CACHE=/tmp/inst-pcache timeout 300 "$T" render "/tmp/grid-$n-$form.gltf" --backend $b \
        --width 1920 --height 1080 --samples 16 --json -o /tmp/grid.png 2>/tmp/grid.err) \
        || line="\"failed: $(tail -c 300 /tmp/grid.err | tr -d '\n"\\')\""
      echo "{\"nodes\": $n, \"form\": \"$form\", \"backend\": \"$b\", \"render\": $line}"
    done
  done
done > "$OUT/instancing.jsonl"
cp /tmp/grid.png "$OUT/instancing-grid.png" 2>/dev/null
fi
if has scale; then
for ms in 0 200; do
  timeout 200 "$T" bench scale --virtual-workers 2000 --scale-seconds 30 --virtual-unit-ms $ms --out /tmp/scale-$ms 2>&1 | grep -v '^bench:'
  cp /tmp/scale-$ms/scale.json "$OUT/scale-$ms.json" 2>/dev/null
done > "$OUT/scale.txt"
fi
if has gpu-tests; then
  # The test binary finds examples/ through the path it was built at.
  [ -e /work/main ] || { mkdir -p /work && ln -s "$PWD" /work/main; }
  CI=true TESSERA_TEST_ADAPTER=NVIDIA timeout 300 .gpu/gpu-tests --test-threads 4 > "$OUT/gpu-tests.txt" 2>&1
  echo "gpu tests exit $?" >> "$OUT/gpu-tests.txt"
fi
# Times "SCENE BACKEND W H SPP [ARGS...]" specs with the old and the new
# build, interleaved (6 pairs, the first left out), from the summary line.
against_old() {
  secs() { "$@" 2>/dev/null | grep -o '  [0-9.]* s  ' | head -1 | tr -d ' s'; }
  echo "== old: $(.gpu/tessera-old --version 2>&1 | head -1); new: $("$T" --version 2>&1 | head -1)"
  for spec in "$@"; do
    set -- $spec
    local scene=$1 backend=$2 w=$3 h=$4 spp=$5; shift 5
    local old=() new=()
    for i in 1 2 3 4 5 6; do
      o=$(secs .gpu/tessera-old render "$scene" --backend "$backend" --width "$w" --height "$h" --samples "$spp" "$@" -o /tmp/old.exr)
      n=$(secs "$T" render "$scene" --backend "$backend" --width "$w" --height "$h" --samples "$spp" "$@" -o /tmp/new.exr)
      # The first pair warms caches (files, the driver's shader cache).
      [ "$i" = 1 ] || { old+=("$o"); new+=("$n"); }
    done
    echo "$scene $backend ${w}x$h $spp spp $*: old ${old[*]} s; new ${new[*]} s"
    printf '%s\n' "${old[@]}" | sort -n | sed -n 3p | xargs -I{} echo "  median old {} s"
    printf '%s\n' "${new[@]}" | sort -n | sed -n 3p | xargs -I{} echo "  median new {} s"
  done
}
if has against-old; then
against_old "examples/resolution.toml cpu 800 600 4" "examples/complexity/glass-9.toml cpu 800 600 4" "examples/depth.toml cpu 800 600 4" \
  "examples/resolution.toml gpu 1920 1080 64" "examples/complexity/glass-9.toml gpu 1920 1080 16" "examples/depth.toml gpu 1920 1080 16" \
  > "$OUT/against-old.txt" 2>&1
fi
# `meshes-against-old` (issue 34; ~2 min): the same for small meshes, whose
# hits read the triangle array and kept normals (World::triangle_normal).
if has meshes-against-old; then
H=.gpu/scenes/gltf/DamagedHelmet/glTF/DamagedHelmet.gltf
against_old "examples/cornell.toml cpu 800 600 16 --integrator path" "examples/cornell.toml cpu 800 600 16" \
  "$H cpu 800 600 16 --integrator path" "$H cpu 800 600 16" \
  "examples/cornell.toml gpu 1920 1080 64 --integrator path" "$H gpu 1920 1080 64 --integrator path" \
  > "$OUT/meshes-against-old.txt" 2>&1
fi
# `big-mesh` (issue 34; ~2 min a size): a heightfield of each of the
# $BIG_MESH triangle counts (default 10000000; several, space-separated;
# scripts/heightfield.py) rendered 160x120 1 spp on all cores and on the
# GPU, `--json` (peak RSS, prepare seconds, gpu_scene_bytes) into
# big-mesh.jsonl, a line a size and backend.
if has big-mesh; then
{
  for n in ${BIG_MESH:-10000000}; do
    python3 scripts/heightfield.py "$n" /tmp/big.gltf
    for backend in cpu gpu; do
      "$T" render /tmp/big.gltf --backend $backend --width 160 --height 120 --samples 1 -o /tmp/big-$backend.png --json
    done
  done
} > "$OUT/big-mesh.jsonl" 2> "$OUT/big-mesh-log.txt"
fi
if has cpu-worker; then
# Issue 15's 1-worker target: the local render in the bench's own process
# against the same render as a whole `tessera render` process (its
# in-process seconds) and against a 1-worker farm, interleaved; and where
# the machine's CPUs lie (SMT siblings), which the placement of two
# threads depends on.
{
  echo "== topology"; nproc; lscpu -e 2>/dev/null | head -20
  for i in 1 2 3 4 5; do
    echo "tessera render --threads 2, 1080p 16 spp, run $i: $("$T" render examples/resolution.toml --width 1920 --height 1080 --samples 16 --threads 2 -o /tmp/cw.png 2>&1 | grep -o '  [0-9.]* s  ' | head -1 | tr -d ' ') in process"
  done
} > "$OUT/cpu-worker.txt" 2>&1
timeout 300 "$T" bench farm --workers 1 --worker-threads 2 --repeat 5 \
  --out /tmp/bench-cw --cache /tmp/bench-cache >> "$OUT/cpu-worker.txt" 2>&1
for i in 1 2 3; do
  echo "tessera render --threads 2, 1080p 16 spp, after the farm, run $i: $("$T" render examples/resolution.toml --width 1920 --height 1080 --samples 16 --threads 2 -o /tmp/cw.png 2>&1 | grep -o '  [0-9.]* s  ' | head -1 | tr -d ' ') in process" >> "$OUT/cpu-worker.txt"
done
fi
if has farm-gpu; then
# Issue 15's GPU worker alone and beside 7 CPU workers, with the
# coordinator's and workers' debug logs (each result's intake by stage).
RUST_LOG=info,tessera_coordinator=debug,tessera_worker=debug timeout 200 "$T" bench farm --workers 1 --worker-threads 2 \
  --gpu-workers 1 --mixed-cpu-workers 7 --out /tmp/bench-g --cache /tmp/bench-cache > "$OUT/farm-gpu.txt" 2>&1
echo "farm-gpu exit $?" >> "$OUT/farm-gpu.txt"
for r in /tmp/bench-g/farm/run-gpu*.coordinator.log; do
  run=${r%.coordinator.log}
  echo "== timeline of ${run##*/}"
  python3 scripts/farm-timeline.py "$run".worker-*.log 2>&1 | head -20
done >> "$OUT/farm-gpu.txt"
for r in /tmp/bench-g/farm/run-gpu*.coordinator.log; do python3 scripts/writer-busy.py "$r"; done >> "$OUT/farm-gpu.txt" 2>&1
if [ -x .gpu/xfer ]; then
  for w in 8388608 33554432; do echo "== xfer, stream window $w, server without nodelay"; WIN=$w .gpu/xfer | tail -8; echo "== xfer, stream window $w, server with nodelay"; NODELAY=1 WIN=$w .gpu/xfer | tail -8; done >> "$OUT/farm-gpu.txt" 2>&1
fi
tar czf "$OUT/farm-gpu-logs.tar.gz" -C /tmp/bench-g/farm --exclude='frames-*' --exclude='data-*' --exclude='*cache-*' . 2>/dev/null
fi
if has farm; then
# The box: calls start fresh boxes that differ (a 2-thread render of the
# same frame took 2.9-6.4 s), so farm figures compare within one call.
{ nproc; grep -m1 'model name' /proc/cpuinfo; uptime; nvidia-smi --query-gpu=name,driver_version --format=csv,noheader; } > "$OUT/farm-machine.txt" 2>&1
echo "== farm: tessera bench farm (CPU workers against the machine's ceiling, 1 GPU worker alone and beside 7 CPU workers)"
timeout 400 "$T" bench farm --workers 1,2,4,8 --worker-threads 2 --gpu-workers 1 --mixed-cpu-workers 7 --repeat 5 \
  --out /tmp/bench --cache /tmp/bench-cache > "$OUT/farm-suite.txt" 2>&1
echo "farm suite exit $?" >> "$OUT/farm-suite.txt"
for r in /tmp/bench/farm/run-*.coordinator.log; do
  run=${r%.coordinator.log}
  echo "== timeline of ${run##*/}"
  python3 scripts/farm-timeline.py "$run".worker-*.log 2>&1 | head -20
done > "$OUT/farm-timeline.txt"
if [ -n "${FARM_DEBUG:-}" ]; then
  # The GPU worker alone again, with the coordinator's debug log (decode,
  # encode, commit and merge times per result batch).
  RUST_LOG=info,tessera_coordinator=debug timeout 120 "$T" bench farm --workers 1 --worker-threads 2 --gpu-workers 1 --mixed-cpu-workers 0 \
    --out /tmp/bench-dbg --cache /tmp/bench-cache > "$OUT/farm-debug.txt" 2>&1
  tar czf "$OUT/farm-debug-logs.tar.gz" -C /tmp/bench-dbg/farm --exclude='frames-*' --exclude='data-*' --exclude='*cache-*' . 2>/dev/null
fi
echo "== latency: warm farm of 2 CPU workers (2 threads) + 1 GPU worker; 64x64 1 spp jobs, then 1080p 16 spp" > "$OUT/farm-latency.txt"
"$T" coordinator --listen 127.0.0.1:7998 --data /tmp/lat-data > /dev/null 2>/tmp/lat-coord.log &
C=$!; sleep 0.5
W=()
for i in 1 2; do "$T" worker --coordinator http://127.0.0.1:7998 --threads 2 --name cpu-$i --cache /tmp/lat-cache-$i 2>/tmp/lat-w$i.log & W+=($!); done
"$T" worker --coordinator http://127.0.0.1:7998 --backend gpu --name gpu --cache /tmp/lat-cache-g 2>/tmp/lat-wg.log & W+=($!)
sleep 3
for i in 1 2 3 4 5 6; do
  s=$EPOCHREALTIME
  id=$("$T" submit examples/resolution.toml --coordinator http://127.0.0.1:7998 --width 64 --height 64 --samples 1 --wait 2>/dev/null)
  e=$EPOCHREALTIME
  awk -v s="$s" -v e="$e" -v i="$i" 'BEGIN { printf "64x64 1 spp job %d: submit to done %.1f ms\n", i, 1000 * (e - s) }' >> "$OUT/farm-latency.txt"
done
for i in 1 2 3; do
  s=$EPOCHREALTIME
  id=$("$T" submit examples/resolution.toml --coordinator http://127.0.0.1:7998 --width 1920 --height 1080 --samples 16 --wait 2>/dev/null)
  e=$EPOCHREALTIME
  "$T" status "$id" --coordinator http://127.0.0.1:7998 --json | python3 -c "
import json, sys
j = json.load(sys.stdin)
print('1080p 16 spp job $i: submit to done %.1f ms, to first merged result %d ms, first lease to last result %d ms' % (1000 * ($e - $s), j['first_result_unix_ms'] - j['submitted_unix_ms'], j['last_result_unix_ms'] - j['first_lease_unix_ms']))" >> "$OUT/farm-latency.txt"
done
kill "${W[@]}" $C 2>/dev/null; wait 2>/dev/null
echo "== batched result throughput (64 results a message)" > "$OUT/farm-throughput.txt"
# A fresh coordinator for each run: one run's 64 load clients stay
# registered after it (until they time out).
for batch in 64 1; do
  rm -rf /tmp/load-data
  "$T" coordinator --listen 127.0.0.1:7999 --data /tmp/load-data > /dev/null 2>&1 &
  C=$!; sleep 1
  timeout 30 .gpu/result_load http://127.0.0.1:7999 examples/resolution.toml 64 5 $batch >> "$OUT/farm-throughput.txt" 2>&1
  kill $C; wait $C 2>/dev/null
done
cp /tmp/bench/farm.csv "$OUT/" 2>/dev/null
tar czf "$OUT/farm-logs.tar.gz" -C /tmp/bench/farm --exclude='frames-*' --exclude='data-*' --exclude='*cache-*' . 2>/dev/null
fi
if has multi-gpu; then
cores=$(nproc)
adapters=${MULTI_GPU_ADAPTERS:-$("$T" gpus --json | python3 -c 'import json, sys; print(",".join(str(a["index"]) for a in json.load(sys.stdin)))')}
cpu_counts=$(for n in 1 2 4 8 16; do [ $((2 * n)) -le "$cores" ] && printf '%s,' "$n"; done)
cpu_counts=${cpu_counts%,}
{
  echo "== machine"; nproc; grep -m1 'model name' /proc/cpuinfo; nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
  echo "== tessera gpus"; "$T" gpus
  echo "== GPU workers on adapters $adapters; mixed runs: (${cores} - N - 1) / 2 CPU workers of 2 threads beside N GPU workers; CPU farm: workers $cpu_counts of 2 threads"
} > "$OUT/multi-gpu-machine.txt" 2>&1
echo "== multi-gpu: tessera bench multi-gpu --gpu-adapters $adapters --mixed-cores $cores"
timeout "${MULTI_GPU_TIMEOUT:-420}" "$T" bench multi-gpu --gpu-adapters "$adapters" --worker-threads 2 --mixed-cores "$cores" ${MULTI_GPU_ARGS:-} \
  --out /tmp/bench --cache /tmp/bench-cache > "$OUT/multi-gpu-suite.txt" 2>&1
echo "multi-gpu suite exit $?" >> "$OUT/multi-gpu-suite.txt"
echo "== multi-gpu: tessera bench farm --workers $cpu_counts --worker-threads 2 (CPU workers alone)"
timeout "${CPU_FARM_TIMEOUT:-240}" "$T" bench farm --workers "$cpu_counts" --worker-threads 2 ${MULTI_GPU_ARGS:-} \
  --out /tmp/bench/cpu-farm --cache /tmp/bench-cache > "$OUT/multi-gpu-cpu-farm.txt" 2>&1
echo "cpu farm exit $?" >> "$OUT/multi-gpu-cpu-farm.txt"
cp /tmp/bench/multi-gpu.csv "$OUT/" 2>/dev/null
cp /tmp/bench/cpu-farm/farm.csv "$OUT/cpu-farm.csv" 2>/dev/null
tar czf "$OUT/multi-gpu-logs.tar.gz" -C /tmp/bench/multi-gpu --exclude='frames-*' --exclude='data-*' --exclude='*cache-*' --exclude='*.png' --exclude='*.svg' . 2>/dev/null
fi
if has farm-image; then
# Issue 36: the error-optimal adaptive mode (`--adaptive-mode image`) on
# the farm against the local render of the same settings: the time from
# submit to done with 1 worker of all cores, 4 of 4 threads and 8 of 2
# (each frame's rounds wait for their last tile), and whether the fetched
# frame is the local image bit for bit. $FARM_IMAGE_ARGS replaces the
# render settings.
S=examples/distributed.toml
FI_ARGS=${FARM_IMAGE_ARGS:---integrator path --width 640 --height 480 --adaptive-mode image --target-error 0.00075 --min-samples 16 --max-samples 1024}
{
  echo "== machine"; nproc; grep -m1 'model name' /proc/cpuinfo
  echo "== settings: $S $FI_ARGS"
  for i in 1 2; do
    s=$EPOCHREALTIME
    "$T" render $S $FI_ARGS -o /tmp/fi-local.png --json > /tmp/fi-local.json 2>/dev/null
    e=$EPOCHREALTIME
    python3 -c "
import json, sys
j = json.load(open('/tmp/fi-local.json')); a = j['adaptive']
print('local render %d (all cores): %.2f s (process %.2f s), %d rounds, mean %.1f spp, estimated image RMSE %.3e' % ($i, j['seconds'], $e - $s, a['rounds'], a['mean_samples'], a['estimated_rms_error']))"
  done
  for cfg in "1 $(nproc)" "4 $(( $(nproc) / 4 ))" "8 $(( $(nproc) / 8 ))"; do
    set -- $cfg
    rm -rf /tmp/fi-data /tmp/fi-frames
    "$T" coordinator --listen 127.0.0.1:7997 --data /tmp/fi-data > /dev/null 2>/tmp/fi-coord.log &
    C=$!; sleep 0.5
    W=()
    for w in $(seq 1 "$1"); do
      "$T" worker --coordinator http://127.0.0.1:7997 --threads "$2" --name "w$w" --cache "/tmp/fi-cache-$w" 2>/dev/null & W+=($!)
    done
    sleep 2
    s=$EPOCHREALTIME
    id=$("$T" submit $S $FI_ARGS --tile-size 64 --coordinator http://127.0.0.1:7997 --wait 2>/dev/null)
    e=$EPOCHREALTIME
    "$T" fetch "$id" -o /tmp/fi-frames --coordinator http://127.0.0.1:7997 > /dev/null 2>&1
    same=$(cmp -s /tmp/fi-frames/frame_0000.png /tmp/fi-local.png && echo "the local image, byte for byte" || echo "DIFFERS from the local image")
    "$T" status "$id" --coordinator http://127.0.0.1:7997 --json | python3 -c "
import json, sys
j = json.load(sys.stdin); a = j['adaptive']
print('farm, $1 workers of $2 threads: submit to done %.2f s, first lease to last result %.2f s, %d pixel-samples, estimated image RMSE %.3e; frame: $same' % ($e - $s, (j['last_result_unix_ms'] - j['first_lease_unix_ms']) / 1000, j['samples_done'], a['estimated_error']))"
    kill "${W[@]}" $C 2>/dev/null; wait 2>/dev/null
  done
} > "$OUT/farm-image.txt" 2>&1
fi
# CSVs and plots only: the per-run images are many and large (phases
# that ran no bench suite have none).
[ -d /tmp/bench ] && tar czf "$OUT/bench-$PHASE.tar.gz" -C /tmp/bench --exclude='*-*x*-s*.png' --exclude='frames-*' --exclude='data-*' .
ls -la "$OUT"
