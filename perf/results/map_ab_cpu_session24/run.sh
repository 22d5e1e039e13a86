#!/bin/bash
# usage: run.sh OUT_DIR ROUND REPEATS TOLERANCE NAME:TREE ...   (each tree's own code under its own PYTHONPATH, in turn;
# TOLERANCE "none" or a number, passed to psf_map by perf/tools/map_warm_repeats.py; default batch)
set -u
out=$1; r=$2; reps=$3; tol=$4; shift 4
py=/work/main/.venv/bin/python
wr=$(cd "$(dirname "$0")/../../tools" && pwd)/map_warm_repeats.py
targ=(); [ "$tol" != none ] && targ=(--tolerance "$tol")
for spec in "$@"; do
    IFS=: read -r name tree <<< "$spec"
    (cd "$tree" && PYTHONPATH="$tree" $py "$wr" --batch 0 --repeats "$reps" "${targ[@]}" \
        --out "$out/wr${r}_${name}_t${tol}.json") 2>&1 | grep -v "CUDA warning" | tail -1 | sed "s/^/$(date -u +%T) r$r $name t$tol: /" | tee -a "$out/warm_repeats.log"
done
