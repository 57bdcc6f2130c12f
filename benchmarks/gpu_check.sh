#!/usr/bin/env bash
# The GPU check of issue 27, in one go (about 7 minutes on one H100/H200):
#   nvdiffrast  its plugin built (first use) and a test triangle rasterized
#   info        `saft info`: where `--device auto` puts physics, renders and appearance
#   pytest      pytest -m cuda (the GPU-only tests, nvdiffrast's included)
#   physics     the solver comparison on CUDA (32x32, 50 frames, forward + backward), the CPU default beside it
#   render      the render benchmark at 700x800 and 350x400: PyTorch and nvdiffrast on CUDA, PyTorch on the CPU
#   r1          R1, texture and shape phases, --device auto: wall time and mean CD2 (set SAFT_PHYSICS_DEVICE
#               to cpu or cuda to override auto's physics device for an A/B run); run right after nvdiffrast
#   r1b         (not in the default steps) R1 with the perturbation of repeat 1, compiled kernels cached
#   r1c         (not in the default steps) the same with the perturbation of repeat 2
#   r1bf16      (not in the default steps) R1 with SAFT_DENSE_SOLVER=densebf16 (now auto's choice as well)
#   profile     (not in the default steps) R1's first 10 frames, 10 final epochs, under torch.profiler: host and
#               device time per part of the shape phase (bench_r1.py --profile)
#   apptest     (not in the default steps; needs Mitsuba: benchmarks/gpu_stage_appearance.sh, a call of its own)
#               phase 3's small fit on cuda_ad_rgb (tests/appearance/test_appearance_cuda.py)
#   appearance  (the same) bench_appearance.py's print scene, phase 3 on CUDA with the CUDA profile cut to
#               SAFT_GPU_APP_EPOCHS epochs (default 200 of its 2000) and the CPU profile: fit wall seconds and
#               the ground-truth metrics
# Then a table, and one line per number (name=value). Each step has its own time limit, so a hung step
# costs its limit, not the check. Choose steps with SAFT_GPU_CHECK_STEPS="physics r1" and the tests with
# SAFT_GPU_CHECK_TESTS="tests/physics" (default: all of both), the solvers of the physics step with
# SAFT_GPU_CHECK_PHYSICS="--solver dense --compile both" (default "--solver all"). On the lent machine of this workplace
# (see ../shared/gpu/stage.sh):
#   bash .gpu/run.sh bash benchmarks/gpu_check.sh
# Logs go to $OUT (the lent machine's folder that comes back) or /tmp/saft-gpu-check: one per step and
# numbers.txt (8 files at most come back); the result folders go to /tmp.
set -u
cd "$(dirname "$0")/.."
out=${OUT:-/tmp/saft-gpu-check}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
py=python3
declare -a rows

step() {   # step NAME LIMIT_S COMMAND...: runs it, keeps its log and its name=value lines
  local name=$1 limit=$2; shift 2
  echo "=== $name: $*"
  local t0=$(date +%s%N)
  timeout "$limit" "$@" > "$out/$name.log" 2>&1
  local rc=$?
  local ms=$(( ($(date +%s%N) - t0) / 1000000 ))
  local dt=$(printf '%d.%03d' $((ms / 1000)) $((ms % 1000)))
  tail -n 25 "$out/$name.log"
  rows+=("$(printf '%-10s rc=%-3s %9s s' "$name" "$rc" "$dt")")
  echo "${name}_rc=$rc"
  echo "${name}_s=$dt"
}

steps=" ${SAFT_GPU_CHECK_STEPS:-nvdiffrast info pytest physics render r1} "
want() { [[ "$steps" == *" $1 "* ]]; }

want nvdiffrast && step nvdiffrast 300 $py -c "
import time; t = time.perf_counter()
from saft.render.nvdiffrast_backend import nvdiffrast_status
ok, why = nvdiffrast_status()
print('nvdiffrast_ok=%d' % ok, why)
print('nvdiffrast_first_use_s=%.1f' % (time.perf_counter() - t))
import sys; sys.exit(0 if ok else 1)"
# R1 first (the headline number), with torch.compile's cache emptied so that its wall time includes the
# physics kernels' compilation, as on a fresh machine. r1b (not in the default steps), run last: R1 again with
# the perturbation of repeat 1 and the compiled kernels from r1's cache, as a user's second run.
r1cache=$(mktemp -d)
want r1 && TORCHINDUCTOR_CACHE_DIR=$r1cache step r1 300 $py benchmarks/bench_r1.py --device auto --out /tmp/saft-gpu-r1
want info && step info 120 $py -m saft info
want pytest && step pytest 300 $py -m pytest -q -m cuda -p no:cacheprovider ${SAFT_GPU_CHECK_TESTS:-tests}
if want physics; then
  step physics 240 $py benchmarks/bench_physics.py --device cuda ${SAFT_GPU_CHECK_PHYSICS:---solver all} --budget-s 1.5
  gpu_s=$(grep -h '^physics_fwdbwd_s=' "$out/physics.log" | cut -d= -f2)
  cpu_s=$(grep -h '^physics_cpu_fwdbwd_s=' "$out/physics.log" | cut -d= -f2)
  faster=$($py -c "print(int(${gpu_s:-1e9} < ${cpu_s:-0}))")
  echo "physics_cuda_faster=$faster" | tee -a "$out/physics.log"   # auto puts R1's physics on CUDA (saft.device): this says whether it should
fi
want render && step render 180 bash -c "$py benchmarks/bench_render.py --device cuda --backend nvdiffrast --threads 1 --runs 20 --profile && \
                         $py benchmarks/bench_render.py --device cuda --backend torch --threads 1 --runs 20 && \
                         $py benchmarks/bench_render.py --device cpu --backend torch --threads 8 --runs 5"
want r1b && TORCHINDUCTOR_CACHE_DIR=$r1cache step r1b 300 $py benchmarks/bench_r1.py --device auto --first-repeat 1 \
                  --out /tmp/saft-gpu-r1b
want r1c && TORCHINDUCTOR_CACHE_DIR=$r1cache step r1c 300 $py benchmarks/bench_r1.py --device auto --first-repeat 2 \
                  --out /tmp/saft-gpu-r1c
want r1bf16 && SAFT_DENSE_SOLVER=densebf16 TORCHINDUCTOR_CACHE_DIR=$r1cache step r1bf16 300 $py benchmarks/bench_r1.py \
                  --device auto --out /tmp/saft-gpu-r1bf16
app="$py benchmarks/bench_appearance.py --root ${SAFT_GPU_APP_ROOT:-.gpu2/appbench} --frames 32 --width 320 \
     --height 240 --fabrics print --device cuda --no-baseline --threads 1"
want apptest && step apptest 200 $py -m pytest -q -m cuda -p no:cacheprovider -s \
                                  tests/appearance/test_appearance_cuda.py
want appearance && step appearance 420 bash -c "$app --profile cuda --set epochs=${SAFT_GPU_APP_EPOCHS:-200} && \
                                              $app --profile cpu"
want profile && step profile 240 $py benchmarks/bench_r1.py --device auto --frames 10 --set shape.final_epochs=10 \
                          --profile --out /tmp/saft-gpu-profile

echo
echo "=== summary"
printf '%s\n' "${rows[@]}"
grep -h -E '^[a-z0-9_]+(_[0-9a-z.x-]+)*=[-0-9.e+]+' "$out"/*.log | sort -u | tee "$out/numbers.txt"
wall=$(grep -hs '^r1_wall_s=' "$out/r1.log" | cut -d= -f2)
cd2=$(grep -hs '^r1_cd2_1e-4m2=' "$out/r1.log" | cut -d= -f2)
echo "r1_gpu_s=${wall:-none}"
echo "r1_gpu_cd2=${cd2:-none}"
