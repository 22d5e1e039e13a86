#!/usr/bin/env bash
# Old against new on the same GPU machine, in one command: the Cooke design step (perf/profile_step.py) and the
# 10 x 10 x 3 A489 + DOE map at 64 px at psf_map's default batch (perf/bench_map.py), each tree in turn.
#   git archive BASE rwwarp torch_bridge kernels perf | tar -x -C ab_old     # here (ab_old/ is untracked)
#   bash perf/tools/ab_gpu.sh ab_old BASE [STEPS]                            # there, after rw-env.sh
# Writes $OUT/ab_{base,new}/ (profile_step_cooke_hybrid_cuda.{txt,json}, bench_map JSON).
set -u
old=$(cd "$1" && pwd); base=$2; steps=${3:-6}
here=$(cd "$(dirname "$0")/../.." && pwd)
out=${OUT:-$here/perf/results}
ln -sfn ../kernels "$old/rwwarp/kernels"
for tree in base new; do
  if [ $tree = base ]; then src=$old; commit=$base; else src=$here; commit=${RWWARP_COMMIT:-worktree}; fi
  mkdir -p "$out/ab_$tree"
  echo "== cooke_hybrid step at $commit ($tree)"
  (cd "$src" && RWWARP_COMMIT=$commit PYTHONPATH=$src${PYTHONPATH:+:$PYTHONPATH} timeout 200 python3 perf/profile_step.py --config cooke_hybrid \
     --preset gpu --device cuda --steps "$steps" --out "$out/ab_$tree" 2>&1 \
     | grep -v "use_ai2\|Warning\|arm = Arm\|warnings.warn" | awk "NR<=8")
  echo "== map at $commit ($tree)"
  (cd "$src/perf" && RWWARP_COMMIT=$commit PYTHONPATH=$src${PYTHONPATH:+:$PYTHONPATH} timeout 150 python3 bench_map.py --device cuda --batch 0 \
     --no-deeplens --out "$out/ab_$tree" 2>&1 | grep -v use_ai2 | tail -4)
done
