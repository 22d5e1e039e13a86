#!/bin/bash
# usage: run.sh OUT_DIR ROUND REPEATS NAME:TREE:BATCH ...   (each tree's own code under its own PYTHONPATH, in turn)
set -u
out=$1; r=$2; reps=$3; shift 3
py=/work/main/.venv/bin/python
wr=$(cd "$(dirname "$0")/../../tools" && pwd)/map_warm_repeats.py
for spec in "$@"; do
    IFS=: read -r name tree batch <<< "$spec"
    (cd "$tree" && PYTHONPATH="$tree" $py "$wr" --batch "$batch" --repeats "$reps" \
        --out "$out/wr${r}_${name}_b${batch}.json") 2>&1 | grep -v "CUDA warning" | tail -1 | sed "s/^/$(date -u +%T) r$r $name: /" | tee -a "$out/warm_repeats.log"
done
