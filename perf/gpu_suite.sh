#!/usr/bin/env bash
# Everything measured on a GPU in one command (device tool): results JSON under $OUT and perf/results.
set -u
export RWWARP_RESULTS=${OUT:-perf/results}
cd "$(dirname "$0")"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
python3 -c "import cupy; print('cupy', cupy.__version__)" || echo "no cupy"
echo "== trace"; timeout 200 python3 bench_trace.py --device cuda --sizes 1000000 16000000 2>&1 | tail -5
echo "== psf";   timeout 300 python3 bench_psf.py --device cuda --deeplens --repeat 3 2>&1 | tail -8
echo "== gpu tests"; cd ../tests && timeout 150 python3 -m pytest -q -p no:cacheprovider rwwarp/test_propagate.py -rs 2>&1 | tail -8
