#!/usr/bin/env bash
# Prepares the second call of a GPU check (issue 27, item 4): phase 3 on CUDA, Mitsuba's cuda_ad_rgb.
# Mitsuba's wheel (62 MB) does not travel beside R1 under the device tool's 64 MiB limit, so this call carries
# .gpu2/ alone (about 35 MB; ignored by git):
#   .gpu2/site.tar.xz  Mitsuba and Dr.Jit, the versions installed here, for the device's Python 3.12, slimmed
#                      to the variants cuda_ad_rgb and scalar_rgb and to the plugins saft can load (29 MB)
#   .gpu2/whl/         the other wheels saft needs there (the list of ../shared/gpu/stage.sh)
#   .gpu2/appbench/    bench_appearance.py's print scene (32 frames, 320 x 240) and its phase-1 texture, from
#                      the benchmark's cache (made here on the CPU when absent: several minutes)
#   .gpu2/run.sh       the wrapper:  bash .gpu2/run.sh COMMAND...
# Run it in the project's root, then (device tool) carry [".gpu2"] and
#   bash .gpu2/run.sh env SAFT_GPU_CHECK_STEPS="apptest appearance" bash benchmarks/gpu_check.sh
set -euo pipefail
root=$(git rev-parse --show-toplevel)
cd "$root"
grep -qx '/.gpu2/' .git/info/exclude 2>/dev/null || echo '/.gpu2/' >> .git/info/exclude
bench=${SAFT_APPEARANCE_BENCH:-/tmp/saft-appearance-bench}
name=print_32f_320x240
mkdir -p .gpu2/whl .gpu2/appbench/scenes .gpu2/appbench/results/$name-texture
pyver() { python3 -c "import importlib.metadata as m; print(m.version('$1'))"; }
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
if [ ! -f .gpu2/site.tar.xz ]; then
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    -d "$tmp/w" "mitsuba==$(pyver mitsuba)" "drjit==$(pyver drjit)" 2>&1 | grep -v '^WARNING' || true
  mkdir -p "$tmp/site"
  for w in "$tmp"/w/*.whl; do (cd "$tmp/site" && python3 -m zipfile -e "$w" .); done
  (cd "$tmp/site" && rm -rf share mitsuba/include mitsuba/cmake mitsuba/pkgconfig mitsuba/mitsuba_stubs drjit/include \
     drjit/cmake mitsuba/llvm_ad_*.so mitsuba/cuda_ad_mono*.so mitsuba/cuda_ad_spectral*.so \
   && cd mitsuba/plugins && rm -f volpath*.so ellipsoids*.so bsplinecurve.so linearcurve.so sdfgrid.so sunsky.so \
     timed_sunsky.so ptracer.so heterogeneous.so aov.so moment.so stokes.so)
  tar -cJf .gpu2/site.tar.xz -C "$tmp/site" .
fi
for w in trimesh tomli-w pygltflib dataclasses-json marshmallow deprecated; do
  ls .gpu2/whl | grep -qi "^$(echo "$w" | tr - _)-" && continue
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d .gpu2/whl "$w" 2>&1 | grep -v '^WARNING' || true
done
if [ ! -f "$bench/results/$name-texture/texture.png" ]; then
  python3 benchmarks/bench_appearance.py --frames 32 --width 320 --height 240 --fabrics print --root "$bench" \
    --no-baseline --no-true-motion
fi
rm -rf ".gpu2/appbench/scenes/$name" && cp -r "$bench/scenes/$name" .gpu2/appbench/scenes/
cp "$bench/results/$name-texture/texture.png" ".gpu2/appbench/results/$name-texture/"
cat > .gpu2/run.sh <<'RUN'
#!/usr/bin/env bash
# On the device machine, in the project's root: Mitsuba, Dr.Jit and the wheels into /tmp/site, src/ on the path.
set -u
export PYTHONUNBUFFERED=1
mkdir -p /tmp/site && tar -xJf .gpu2/site.tar.xz -C /tmp/site || { echo "Mitsuba unpack failed"; exit 1; }
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .gpu2/whl/*.whl \
  >/tmp/gpu-pip.log 2>&1 || { echo "wheel install failed:"; tail -5 /tmp/gpu-pip.log; exit 1; }
export PYTHONPATH="/tmp/site:$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
nvidia-smi -L 2>/dev/null
"$@"
RUN
du -sh .gpu2
echo 'now: device run  carry=[".gpu2"]  command="bash .gpu2/run.sh env SAFT_GPU_CHECK_STEPS=\"apptest appearance\" bash benchmarks/gpu_check.sh"'
