#!/usr/bin/env bash
# The paper's design experiments on a GPU machine: one arm and seed per GPU, in the background
# (perf/results/design/PROTOCOL.md, sections 4 and 6), watched, stopped, packed and collected by later
# device commands. Run from the repository root, after `source ~/rw-env.sh`.
#
#   bash perf/tools/arms_gpu.sh start EXPERIMENT SEED:ARM ...   # run k on GPU k, detached; a run whose pack
#                                  # is in out/pack/<name>/ (pack.json + parts) resumes from it. ARMS_PROCS=N: each
#                                  # run on N GPUs (rwwarp design --procs N: its PSF nodes and batch split over N ranks),
#                                  # run k on GPUs kN .. kN+N-1 (after ARMS_GPU0)
#   bash perf/tools/arms_gpu.sh watch SECONDS                   # every run's status every 30 s, for SECONDS
#   bash perf/tools/arms_gpu.sh wait SECONDS                    # until every run's process has ended (or SECONDS),
#                                  # then each run's status: finish an arm and collect it in the same call
#   bash perf/tools/arms_gpu.sh stop                            # SIGTERM every live run: it ends at once, its
#                                  # last checkpoint (every 200 steps) is what a resume starts from
#   bash perf/tools/arms_gpu.sh pack NAME [OPTIONS]             # portable checkpoint of a stopped run (bfloat16
#                                  # weights and Adam moments, parts of <= 15 MiB; OPTIONS replace those of
#                                  # `rwwarp design pack`, e.g. --weights bfloat16 --optimizer none) in out/pack/NAME
#   bash perf/tools/arms_gpu.sh send NAME FIRST COUNT           # parts FIRST.. of that pack (and pack.json) to $OUT
#   bash perf/tools/arms_gpu.sh collect NAME ...                # each run's results and log, no checkpoints, as
#                                  # $OUT/NAME.tar.gz.part00 ... (15 MB parts: cat them to NAME.tar.gz)
#   bash perf/tools/arms_gpu.sh smoke [PARTS]                   # the GPU smoke (perf/gpu_suite.sh smoke-parallel,
#                                  # default: the balanced four parts) detached beside the runs, in out/smoke/; `wait`
#                                  # and `watch` print its state; its memory check is per process, so the runs' do not count
#   bash perf/tools/arms_gpu.sh smoke-collect                   # its JSON, logs and pytest log as $OUT/smoke.tgz (the
#                                  # folder itself holds ~2 GB of its runs' checkpoints)
#
# Export RWWARP_COMMIT first: the copied tree has no .git, and each run records the commit it ran.
# Run folders: out/design/runs/<experiment>_gpu_s<seed>_<arm> (NAME is that last part). The protocol's
# options are set on the command line; the configs stay as they are. Data: carry data/debian-photos.
set -u
RUNS=out/design/runs
PACKS=out/pack
DESIGN="python3 -m torch_bridge.train"
protocol=(--preset ${ARMS_PRESET:-gpu} --set train.joint_steps=2000 --set train.finetune_steps=1000
          --set train.checkpoint_every=200 --set train.log_every=20 --set train.image_every=500
          --set data.root=data/debian-photos --set 'eval.grid=[10,10]' --set eval.node_chunk=16)
# ARMS_SET: more options after the protocol's, e.g. ARMS_SET="--set train.finetune_steps=500" (the protocol's
# rule when a step is slower than planned); ARMS_PRESET: another preset (the CPU rehearsal uses cpu)
read -r -a extra <<< "${ARMS_SET:-}"
# alive RUN_DIR: exit 0 while the run's process lives (its pid and start time in run.pid, read from /proc with the
# standard library only: a broken import of the project must not make a live run look stopped)
alive() {
  python3 - "$1/run.pid" <<'PY'
import json, os, sys
try:
    r = json.load(open(sys.argv[1]))
    stat = open(f"/proc/{int(r['pid'])}/stat").read()
except (OSError, ValueError, KeyError):
    sys.exit(1)
f = stat[stat.rindex(")") + 2:].split()
sys.exit(0 if f[0] != "Z" and int(f[19]) == int(r.get("start_ticks", f[19])) else 1)
PY
}
cmd=${1:?start, watch, wait, stop, pack, send, collect, smoke or smoke-collect}; shift
SMOKE=out/smoke
# smoke_state: one line, the detached smoke's state (nothing when none was started)
smoke_state() {
  [ -f $SMOKE/smoke.pid ] || return 0
  if kill -0 $(cat $SMOKE/smoke.pid) 2>/dev/null; then echo "smoke: running ($(grep -c '^PASS\|^FAIL' $SMOKE/*.log 2>/dev/null \
    | awk -F: '{s += $2} END {print s + 0}') arm(s) done)"
  else tail -1 $SMOKE/smoke.txt 2>/dev/null; fi
}
case $cmd in start|watch|wait|stop|pack|smoke)
  # the device tool copies the tree afresh each call, without the rwwarp/kernels link the checkout's setup made
  [ -d rwwarp ] && [ ! -e rwwarp/kernels ] && ln -sfn ../kernels rwwarp/kernels
  # the project and its GPU wheels come from ~/rw-env.sh; without it every status line is an ImportError traceback
  python3 -c "import torch_bridge, warp" 2>/dev/null \
    || { echo "arms_gpu: torch_bridge or warp does not import (run 'source \$HOME/rw-env.sh' first):" >&2
         python3 -c "import torch_bridge, warp" 2>&1 | tail -1 >&2; exit 2; } ;;
esac
case $cmd in
start)
  exp=${1:?experiment}; shift
  [ -f data/debian-photos/MANIFEST.json ] || { echo "data/debian-photos is missing: carry it" >&2; exit 2; }
  # ARMS_GPU0: the first GPU to use (runs started by an earlier call hold the ones before it); ARMS_NGPU: the GPUs
  # there are (default: nvidia-smi's count; the CPU rehearsal sets it, the ranks then run on the CPU with gloo)
  ngpu=${ARMS_NGPU:-$(nvidia-smi -L | wc -l)}; k=${ARMS_GPU0:-0}; procs=${ARMS_PROCS:-1}
  for sa in "$@"; do
    seed=${sa%%:*}; arm=${sa#*:}
    [ $((k + procs)) -le $ngpu ] || { echo "start: $ngpu GPU(s) for $# runs of $procs GPU(s) each" >&2; exit 2; }
    name=${exp}_gpu_s${seed}_${arm}
    resume=()
    # a pack folder without its pack.json is a trip cut short (session 23: two of three carrying calls were refused
    # and the run silently started from step 0): refuse, rather than throw the pack's steps away
    if [ -d $PACKS/$name ] && [ ! -f $PACKS/$name/pack.json ]; then
      echo "start: $PACKS/$name holds $(ls $PACKS/$name | wc -l) file(s) but no pack.json: send the rest of the pack" \
           "(perf/tools/pack_out.sh) or remove the folder to start $name from step 0" >&2; exit 2
    fi
    [ -f $PACKS/$name/pack.json ] && resume=(--resume $PACKS/$name)
    mkdir -p $RUNS
    gpus=$(seq -s, $k $((k + procs - 1)))
    CUDA_VISIBLE_DEVICES=$gpus $DESIGN $exp --arm $arm "${protocol[@]}" "${extra[@]}" --set seed=$seed --out $RUNS/$name \
      --no-progress --procs $procs "${resume[@]}" --detach || echo "start: $name did not start" >&2
    echo "start: $name on GPU(s) $gpus ${resume[*]}"
    k=$((k + procs))
  done
  ;;
watch)
  secs=${1:-540}; t0=$(date +%s)
  while :; do
    for d in $RUNS/*/; do
      [ -f $d/run.pid ] || continue
      echo "$(date -u +%H:%M:%S) $(basename $d): $($DESIGN status $d 2>&1 | head -2 | tr '\n' ' ')"
    done
    smoke_state
    n=$(for d in $RUNS/*/; do alive $d && echo x; done | wc -l)
    [ $n -gt 0 ] || { echo "watch: no run alive"; break; }
    [ $(( $(date +%s) - t0 + 30 )) -lt $secs ] || break
    sleep 30
  done
  nvidia-smi --query-gpu=index,memory.used,utilization.gpu --format=csv,noheader
  ;;
wait)
  # block until every run has ended (its process gone) or SECONDS have passed, then print each run's status
  secs=${1:-540}; t0=$(date +%s)
  while [ $(( $(date +%s) - t0 + 10 )) -lt $secs ]; do
    n=$(for d in $RUNS/*/; do [ -f $d/run.pid ] && alive $d && echo x; done | wc -l)
    [ $n -gt 0 ] || break
    sleep 10
  done
  for d in $RUNS/*/; do
    if [ -f $d/run.pid ]; then
      echo "$(date -u +%H:%M:%S) $(basename $d): $($DESIGN status $d 2>&1 | head -2 | tr '\n' ' ')"
    fi
  done
  smoke_state
  ;;
smoke)
  parts=${*:-cooke_hybrid a489_aberration+a489_edof:raywave_doe a489_edof:paraxial_doe tests}
  [ -f $SMOKE/smoke.pid ] && kill -0 $(cat $SMOKE/smoke.pid) 2>/dev/null && { echo "smoke: already running" >&2; exit 2; }
  rm -rf $SMOKE; mkdir -p $SMOKE
  OUT=$PWD/$SMOKE setsid nohup bash perf/gpu_suite.sh smoke-parallel $parts > $SMOKE/smoke.txt 2>&1 < /dev/null &
  echo $! > $SMOKE/smoke.pid
  echo "smoke: started (pid $(cat $SMOKE/smoke.pid); parts $parts); log $SMOKE/smoke.txt"
  ;;
smoke-collect)
  [ -d $SMOKE ] || { echo "smoke-collect: no $SMOKE (run 'smoke' first)" >&2; exit 2; }
  smoke_state
  (cd $SMOKE && find . -type f -size -3M \( -name '*.json' -o -name '*.log' -o -name '*.txt' \) | tar czf $OUT/smoke.tgz -T -)
  echo "smoke-collect: $OUT/smoke.tgz $(du -h $OUT/smoke.tgz | cut -f1)"
  ;;
stop)
  for d in $RUNS/*/; do
    [ -f $d/run.pid ] || continue
    if alive $d; then
      pid=$(python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['pid'])" $d/run.pid)
      kill -TERM -- -$pid 2>/dev/null || kill -TERM $pid
      echo "stop: $(basename $d) (pid $pid)"
    fi
  done
  for i in $(seq 30); do
    n=$(for d in $RUNS/*/; do alive $d && echo x; done | wc -l)
    [ $n -eq 0 ] && break; sleep 2
  done
  for d in $RUNS/*/; do echo "$(basename $d): $($DESIGN status $d 2>&1 | head -2 | tr '\n' ' ')"; done
  ;;
pack)
  name=${1:?run name}; shift
  # more options after NAME replace the defaults, e.g. `pack NAME --weights bfloat16 --optimizer none` (33 MiB: a
  # fixed-optics arm's network, Adam restarts on resume; PROTOCOL.md section 6's table)
  opts=(--weights bfloat16 --optimizer bfloat16); [ $# -gt 0 ] && opts=("$@")
  rm -rf $PACKS/$name.new
  $DESIGN pack $RUNS/$name "${opts[@]}" --out $PACKS/$name.new \
    && rm -rf $PACKS/$name && mv $PACKS/$name.new $PACKS/$name && ls -l $PACKS/$name
  ;;
send)
  name=${1:?run name}; first=${2:-0}; count=${3:-4}
  mkdir -p $OUT/$name
  cp $PACKS/$name/pack.json $OUT/$name/
  for f in $(ls $PACKS/$name | grep '^pack\.part' | sort | tail -n +$((first + 1)) | head -$count); do
    cp $PACKS/$name/$f $OUT/$name/
  done
  ls $OUT/$name
  ;;
collect)
  # the device tool brings back files under ~16 MB (session 22: a 17 MB tar did not come back): the tar goes in
  # parts of 15 MB, NAME.tar.gz.part00 ..., joined here with: cat NAME.tar.gz.part* > NAME.tar.gz
  for name in "$@"; do
    tar czf /tmp/$name.tar.gz -C $RUNS --exclude='*.pt' --exclude=pack --exclude=run.pid $name && \
      split -b 15000000 -d /tmp/$name.tar.gz $OUT/$name.tar.gz.part && \
      echo "collect: $name $(du -h /tmp/$name.tar.gz | cut -f1) in $(ls $OUT/$name.tar.gz.part* | wc -l) part(s)," \
           "sha256 $(sha256sum /tmp/$name.tar.gz | cut -c1-16)" && rm -f /tmp/$name.tar.gz
  done
  ;;
*) echo "unknown command $cmd" >&2; exit 2 ;;
esac
