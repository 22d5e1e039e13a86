#!/bin/bash
# The A/B of this directory's README: each tree's own perf/bench_map.py under its own PYTHONPATH, alternating,
# two rounds. Trees: 0550a31 (the issue's baseline), 2247a5a (this session's start), the new commit (this tree).
# usage: run.sh OUT_DIR OLD0550_TREE OLD2247_TREE NEW_TREE
set -u
out=$1; t0550=$2; t2247=$3; tnew=$4
py=/work/main/.venv/bin/python
one() {   # name tree batch
    local name=$1 tree=$2 batch=$3 tmp
    tmp=$(mktemp -d)
    (cd "$tree" && PYTHONPATH="$tree" $py perf/bench_map.py --grid 10 --size 32 --no-deeplens --batch "$batch" --out "$tmp") \
        > "$out/$name.log" 2>&1
    mv "$tmp"/bench_map_cpu.json "$out/$name.json"
    rmdir "$tmp"
    echo "$(date -u +%T) $name: $(grep -h 'rwwarp batch' "$out/$name.log")"
}
for r in 1 2; do
    one old0550_$r "$t0550" 9
    one old2247_$r "$t2247" 9
    one new_$r "$tnew" 9
    one new0_$r "$tnew" 0
done
