#!/usr/bin/env bash
# Everything measured on a GPU in one command (device tool): results JSON under $OUT (or perf/results).
set -u
export RWWARP_RESULTS=${OUT:-$(cd "$(dirname "$0")" && pwd)/results}
cd "$(dirname "$0")"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
echo "== trace"; timeout 100 python3 bench_trace.py --device cuda --sizes 1000000 16000000 2>&1 | tail -4
echo "== psf";   timeout 150 python3 bench_psf.py --device cuda --deeplens --repeat 3 2>&1 | grep -v use_ai2 | tail -4
echo "== map";   timeout 200 python3 bench_map.py --device cuda 2>&1 | grep -v use_ai2 | tail -8
echo "== profile"; timeout 60 python3 profile_psf.py cuda 2>&1 | grep -v "^$" | cut -c1-130 | sed -n 1,22p
echo "== bridge"; timeout 150 python3 bench_bridge.py --device cuda --check results/bench_bridge_reference_cpu.json 2>&1 | tail -4
timeout 200 python3 bench_bridge.py --device cuda 2>&1 | tail -6
echo "== speed/accuracy"; timeout ${SA_TIMEOUT:-170} python3 speed_accuracy.py --device cuda --out "$RWWARP_RESULTS" 2>&1 | grep -v use_ai2 | tail -12
