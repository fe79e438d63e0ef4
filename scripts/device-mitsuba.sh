#!/usr/bin/env bash
# Packs Mitsuba 3 (cuda_ad_rgb and scalar_rgb only) for the NVIDIA benchmark
# machine: its python3 is 3.12 and it cannot download, and the call's whole
# working tree is capped at 64 MiB while the two wheels are 67 MB. The
# other variants, the spectral table, unused plugins and headers are left
# out and the rest is stripped and xz-packed: .gpu/mitsuba.tar.xz (~18 MB),
# unpacked by scripts/device-bench.sh's path-bench phase onto PYTHONPATH.
set -euo pipefail
cd "$(dirname "$0")/.."
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 -d "$work/whl" mitsuba==3.9.1 drjit==1.5.0
mkdir -p "$work/site"
for w in "$work"/whl/*.whl; do python3 -m zipfile -e "$w" "$work/site"; done
cd "$work/site"
rm -rf share mitsuba/include mitsuba/cmake mitsuba/pkgconfig mitsuba/mitsuba_stubs drjit/include drjit/cmake \
  mitsuba/llvm_ad_* mitsuba/cuda_ad_mono* mitsuba/cuda_ad_spectral* mitsuba/scalar_mono* mitsuba/scalar_spectral* \
  mitsuba/data/srgb.coeff
(cd mitsuba/plugins && rm -f ellipsoids.so ellipsoidsmesh.so volpath.so volpathmis.so bsplinecurve.so linearcurve.so \
  sdfgrid.so sunsky.so timed_sunsky.so ptracer.so cylinder.so hair.so measured.so measured_polarized.so aov.so \
  pplastic.so projector.so batch.so gridvolume.so principledthin.so)
find . -name '*.so' -exec strip --strip-unneeded {} \;
cd - >/dev/null
mkdir -p .gpu
tar cf - -C "$work/site" mitsuba drjit | xz -6 -T0 > .gpu/mitsuba.tar.xz
ls -l .gpu/mitsuba.tar.xz
