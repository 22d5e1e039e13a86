#!/usr/bin/env bash
# Old against new on the same GPU machine, in one command: the Cooke design step (perf/profile_step.py) and the
# 10 x 10 x 3 A489 + DOE map at 64 px at psf_map's default batch (perf/bench_map.py), the trees alternating
# (base, new, base, new, ...) so that the machine's drift falls on both.
#   git archive BASE rwwarp torch_bridge kernels perf | tar -x -C ab_old     # here (ab_old/ is untracked; carry
#                                                                            # it after the staging calls)
#   bash perf/tools/ab_gpu.sh ab_old BASE [STEPS [REPEATS]]                  # there, after rw-env.sh
# STEPS: timed design steps a run (default 6); REPEATS: runs of each tree (default 1; each run is a design-step
# profile and a map). Writes $OUT/ab_{base,new}_<run>/ (profile_step_cooke_hybrid_cuda.{txt,json}, bench_map JSON)
# and prints each run's step times and PSF/s.
set -u
old=$(cd "$1" && pwd); base=$2; steps=${3:-6}; repeats=${4:-1}
here=$(cd "$(dirname "$0")/../.." && pwd)
out=${OUT:-$here/perf/results}
ln -sfn ../kernels "$old/rwwarp/kernels"
for run in $(seq 1 "$repeats"); do
  for tree in base new; do
    if [ $tree = base ]; then src=$old; commit=$base; else src=$here; commit=${RWWARP_COMMIT:-worktree}; fi
    dir="$out/ab_${tree}_$run"
    mkdir -p "$dir"
    echo "== cooke_hybrid step at $commit ($tree, run $run)"
    # (awk reads to the end: a reader that stops early, as head does, would kill the profile before it writes)
    (cd "$src" && RWWARP_COMMIT=$commit PYTHONPATH=$src${PYTHONPATH:+:$PYTHONPATH} timeout 200 python3 \
       perf/profile_step.py --config cooke_hybrid --preset gpu --device cuda --steps "$steps" --out "$dir" 2>&1 \
       | grep -v "use_ai2\|Warning\|arm = Arm\|warnings.warn" | awk "NR<=8")
    echo "== map at $commit ($tree, run $run)"
    (cd "$src/perf" && RWWARP_COMMIT=$commit PYTHONPATH=$src${PYTHONPATH:+:$PYTHONPATH} timeout 150 python3 \
       bench_map.py --device cuda --batch 0 --no-deeplens --out "$dir" 2>&1 | grep "PSF/s")
  done
done
