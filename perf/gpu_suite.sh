#!/usr/bin/env bash
# Everything measured on a GPU, in three parts that each fit one device-tool command (<= 10 min):
#   bash perf/gpu_suite.sh a   # trace, single PSF vs DeepLens, 10x10x3 map vs DeepLens, latency profile
#   bash perf/gpu_suite.sh b   # torch bridge: CPU/CUDA gradient check, DeepLens psf+backward, tile study
#   bash perf/gpu_suite.sh c   # speed/accuracy chart, GPU tests
#   bash perf/gpu_suite.sh d   # design smoke run: a489_aberration's gpu preset cut to 40 + 40 steps
#   bash perf/gpu_suite.sh e   # focal PSFs (Cooke, AC254, A489), the Cooke F/4 joint step, the paper maps on 1 and 2 GPUs
#   bash perf/gpu_suite.sh f   # the cooke_hybrid gpu preset's design step profiled, the Warp kernel tests on CUDA, GPU tests
#   bash perf/gpu_suite.sh smoke [PARTS]  # the GPU smoke command: every arm of each gpu preset 3 steps inside the
#                              # preset's memory_budget_gb (perf/smoke_presets.py), then pytest -m gpu. PARTS (default
#                              # all): any of cooke_hybrid a489_aberration a489_edof tests; each part fits one
#                              # 10-minute device command, e.g. `smoke cooke_hybrid a489_aberration` then
#                              # `smoke a489_edof tests`. Exits non-zero when anything fails.
#   bash perf/gpu_suite.sh smoke-parallel [PARTS]  # the same parts at once, part k alone on GPU k; a part may
#                              # name one arm (CONFIG:ARM) and parts joined by + share a GPU one after the other,
#                              # e.g. the balanced four-GPU smoke (~230 s against 320 s, by session 22's part times):
#                              #   smoke-parallel cooke_hybrid a489_aberration+a489_edof:raywave_doe \
#                              #                  a489_edof:paraxial_doe tests
#                              # Memory is checked per process (the arm's own, from the driver's per-process figures),
#                              # so the smoke may share the GPUs with design runs started before it (arms_gpu.sh);
#                              # SMOKE_MEMORY=device checks the whole device's used memory instead (GPUs to itself).
#                              # (CUDA_VISIBLE_DEVICES; a machine with >= as many GPUs as parts, e.g. nvidia-h100-x4;
#                              # with fewer GPUs, part k queues on GPU k mod the GPU count, after the parts before it):
#                              # each part keeps one whole card, so its peak is what it is on one H100; logs in
#                              # $RWWARP_RESULTS/smoke_<part>.log, results in $RWWARP_RESULTS/smoke_<part>/
# Results JSON under $OUT (device tool) or perf/results.
set -u
part=${1:-a}
export RWWARP_RESULTS=${OUT:-$(cd "$(dirname "$0")" && pwd)/results}
SELF="$(cd "$(dirname "$0")" && pwd)/$(basename "$0")"
cd "$(dirname "$0")"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
case $part in
smoke)
  shift
  parts=${*:-cooke_hybrid a489_aberration a489_edof tests}
  rc=0
  # a part is a config (all its arms), CONFIG:ARM (that arm alone) or tests
  configs=$(echo $parts | tr ' ' '\n' | grep -v '^tests$' | cut -d: -f1 | awk '!seen[$0]++' | tr '\n' ' ')
  arms=$(echo $parts | tr ' ' '\n' | grep ':' | tr '\n' ' ')
  if [ -n "$configs" ]; then
    PYTHONUNBUFFERED=1 python3 smoke_presets.py --configs $configs ${arms:+--arms $arms} --memory ${SMOKE_MEMORY:-process} \
      --out "$RWWARP_RESULTS" 2>&1 \
      | grep --line-buffered -v use_ai2
    rc=${PIPESTATUS[0]}
  fi
  if echo " $parts " | grep -q " tests "; then
    # the whole pytest log is kept (session 20's smoke kept only its tail and lost the failures' reasons)
    echo "== GPU tests"; (cd ../tests && timeout 300 python3 -m pytest -q -p no:cacheprovider -m gpu -rf 2>&1 \
      | tee "$RWWARP_RESULTS/pytest_gpu.log" | grep -E "^(FAILED|ERROR)|passed|failed" | tail -20; exit ${PIPESTATUS[0]}) || rc=1
  fi
  echo "smoke: $([ $rc = 0 ] && echo passed || echo FAILED) (parts: $parts)"
  exit $rc
  ;;
smoke-parallel)
  shift
  parts=${*:-cooke_hybrid a489_aberration a489_edof tests}
  ngpu=$(nvidia-smi -L | wc -l)
  # more parts than GPUs: part k joins GPU (k mod ngpu)'s queue, one after the other there (session 25: one H200 was
  # given three parts, part 0 started and the rest were refused, and the smoke looked passed on part 0 alone)
  read -r -a plist <<< "$parts"
  if [ ${#plist[@]} -gt $ngpu ]; then
    groups=()
    for i in "${!plist[@]}"; do g=$((i % ngpu)); groups[$g]="${groups[$g]:+${groups[$g]}+}${plist[$i]}"; done
    echo "smoke-parallel: ${#plist[@]} parts on $ngpu GPU(s): ${groups[*]}"
    parts="${groups[*]}"
  fi
  k=0; pids=()
  # PARTS joined by + run one after the other on one GPU (e.g. a489_aberration+a489_edof:raywave_doe); file names
  # take the part with : and + replaced by - (the device tool brings back plain names only)
  for p in $parts; do
    f=$(echo "$p" | tr ':+' '--')
    mkdir -p "$RWWARP_RESULTS/smoke_$f"
    OUT="$RWWARP_RESULTS/smoke_$f" CUDA_VISIBLE_DEVICES=$k bash "$SELF" smoke $(echo "$p" | tr '+' ' ') \
      > "$RWWARP_RESULTS/smoke_$f.log" 2>&1 &
    pids+=($!); k=$((k + 1))
  done
  rc=0; k=0
  for p in $parts; do
    wait ${pids[$k]} || rc=1
    f=$(echo "$p" | tr ':+' '--')
    echo "== $p (GPU $k)"; grep -v "^ *$" "$RWWARP_RESULTS/smoke_$f.log" | tail -12
    k=$((k + 1))
  done
  echo "smoke-parallel: $([ $rc = 0 ] && echo passed || echo FAILED) (parts: $parts)"
  exit $rc
  ;;
a)
  echo "== trace";   timeout 90 python3 bench_trace.py --device cuda --sizes 1000000 16000000 2>&1 | tail -4
  echo "== psf";     timeout 150 python3 bench_psf.py --device cuda --deeplens --repeat 5 2>&1 | grep -v use_ai2 | tail -4
  echo "== latency"; timeout 60 python3 profile_latency.py cuda --reps 30 2>&1 | grep -v "^$" | cut -c1-150 | sed -n 1,25p \
                       | tee "$RWWARP_RESULTS/profile_latency_gpu.txt"
  echo "== map";     timeout 240 python3 bench_map.py --device cuda 2>&1 | grep -v use_ai2 | tail -8
  ;;
b)
  echo "== bridge check"; timeout 150 python3 bench_bridge.py --device cuda --check results/bench_bridge_reference_cpu.json 2>&1 | tail -4
  echo "== bridge";  timeout 400 python3 bench_bridge.py --device cuda --study --deeplens --no-map 2>&1 | grep -v use_ai2 | tail -20
  ;;
c)
  echo "== speed/accuracy"; timeout ${SA_TIMEOUT:-400} python3 speed_accuracy.py --device cuda --out "$RWWARP_RESULTS" 2>&1 | grep -v use_ai2 | tail -14
  echo "== GPU tests"; (cd ../tests && timeout 150 python3 -m pytest -q -m gpu 2>&1 | tail -4)
  ;;
d)
  # the a489_aberration gpu preset, cut to 12 + 4 steps with a log line per step (wall time and the
  # device's used memory per step in metrics.csv)
  python3 - <<'PY'
import os
import yaml
import torch_bridge
name = os.environ.get("SMOKE_CONFIG", "a489_aberration")
c = yaml.safe_load(open(os.path.join(os.path.dirname(torch_bridge.__file__), "configs", name + ".yaml")))
c["presets"]["gpu"]["train"].update(joint_steps=int(os.environ.get("SMOKE_JOINT", 12)),
                                    finetune_steps=int(os.environ.get("SMOKE_FINETUNE", 4)),
                                    log_every=int(os.environ.get("SMOKE_LOG", 1)),
                                    image_every=0, checkpoint_every=0)
c["presets"]["gpu"]["data"]["eval_images"] = int(os.environ.get("SMOKE_EVAL", 8))
yaml.safe_dump(c, open(os.path.join(os.environ["RWWARP_RESULTS"], name + "_gpu_smoke.yaml"), "w"))
PY
  S=${SMOKE_CONFIG:-a489_aberration}_gpu_smoke
  timeout ${SMOKE_TIMEOUT:-500} python3 -m torch_bridge.train "$RWWARP_RESULTS/$S.yaml" --preset gpu \
      --arm ${SMOKE_ARM:-e2e_doe} --out "$RWWARP_RESULTS/$S" --no-progress 2>&1 | grep -v "use_ai2\|SamplingWarning\|self._build" | tail -25
  cat "$RWWARP_RESULTS"/$S/*/metrics.csv
  # the field builds: batches of nodes and the library's peak estimate against the budget (GB)
  python3 - <<'PY'
import glob, json, os
S = os.environ.get("SMOKE_CONFIG", "a489_aberration") + "_gpu_smoke"
for f in sorted(glob.glob(os.path.join(os.environ["RWWARP_RESULTS"], S, "*", "result.json"))):
    r = json.load(open(f))
    for e in r.get("field_build", []):
        print(f"{r['arm']}: wl {e['key'][0]:.3f} um  {e['nsrc']} nodes in {e['batches']} batches of {e['batch']}  "
              f"ray grid {e['ray_grid']}  n_grid {e['n_grid']}  n_pad {e['n_pad']}  peak est. {e['peak'] / 1e9:.1f} GB / budget {e['budget'] / 1e9:.1f} GB")
    for e in r.get("step_log", [])[-3:]:
        print(f"{r['arm']}: step chunks {e}")
    print({k: r.get(k) for k in ("steps_done", "train_wall_s", "eval_wall_s", "objective_initial", "objective_final")})
    print("replans:", [(e["key"], e["reason"]) for e in r.get("replan_log", [])][:12])
PY
  nvidia-smi --query-gpu=memory.used,memory.total --format=csv,noheader
  ;;
e)
  echo "== focal";  timeout 150 python3 bench_focal_gpu.py "$RWWARP_RESULTS" 2>&1 | grep -v use_ai2 | tail -12
  echo "== cooke f4"; timeout 240 python3 bench_cooke_f4.py --device cuda --out "$RWWARP_RESULTS" --steps 3 2>&1 \
                        | grep -v "use_ai2\|SamplingWarning" | tail -12
  echo "== paper maps"; timeout ${MAP_TIMEOUT:-300} python3 bench_distributed.py --problem paper --only map --device cuda \
                        --ranks ${MAP_RANKS:-1 2} --repeat 2 --out "$RWWARP_RESULTS" 2>&1 | grep -v use_ai2 | tail -20
  ;;
f)
  echo "== design step profile"; timeout 300 python3 profile_step.py --config cooke_hybrid --preset gpu --device cuda \
                        --steps 3 --out "$RWWARP_RESULTS" 2>&1 | grep -v "use_ai2\|UserWarning\|arm = Arm" | head -${PROFILE_LINES:-60}
  echo "== kernel tests";  (cd ../tests && timeout 150 python3 -m pytest -q kernels 2>&1 | tail -3)
  echo "== GPU tests";     (cd ../tests && timeout 200 python3 -m pytest -q -m gpu 2>&1 | tail -3)
  echo "== cooke f4";      timeout 240 python3 bench_cooke_f4.py --device cuda --out "$RWWARP_RESULTS" --steps 3 2>&1 \
                           | grep -v "use_ai2\|SamplingWarning" | tail -8
  ;;
esac
