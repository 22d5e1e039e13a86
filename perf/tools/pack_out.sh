#!/usr/bin/env bash
# A run's pack (out/pack/NAME: pack.json + 15 MiB parts, `arms_gpu.sh pack` / `rwwarp design pack`) laid out for the
# trip to a GPU machine: the device tool carries at most 64 MiB a call with the repository's tree (tracked and
# untracked-not-ignored files, ~20 MB and growing with the results), so the parts go in folders .device/NAME.inK of at
# most PER parts each, pack.json in the first. PER's default is what fits beside the tree as it is now, with 4 MiB to
# spare (session 23: 3 parts, 46 MB, no longer fitted beside a 20 MB tree and two calls were refused).
# Run from the repository root; then one call per folder, in order (the first may also start other work):
#   carry [".device/NAME.inK"], command: mkdir -p out/pack/NAME && cp .device/NAME.inK/* out/pack/NAME/
# and after the last one `bash perf/tools/arms_gpu.sh start ...` finds out/pack/NAME and resumes from it (it checks
# every part's sha256 against pack.json). A call that also carries data/debian-photos (12 MiB) takes at most 2 parts.
#   bash perf/tools/pack_out.sh NAME [PER]
set -euo pipefail
name=${1:?run name (a folder of out/pack)}
src=out/pack/$name
[ -f $src/pack.json ] || { echo "pack_out: $src/pack.json not found" >&2; exit 2; }
# the tree that travels with every call (bytes), and the largest part
tree=$( (git ls-files -z; git ls-files -z --others --exclude-standard) | xargs -0 -r stat -L -c %s 2>/dev/null \
        | awk '{s += $1} END {print s + 0}')
part=$(stat -c %s $(ls -d $src/pack.part* | head -1) 2>/dev/null || echo 15728640)
room=$((64 * 1048576 - tree - 4 * 1048576))
per=${2:-$((room / part))}
[[ $per =~ ^-?[0-9]+$ ]] && [ $per -ge 1 ] || { echo "pack_out: no room for one part beside the $((tree / 1048576)) MiB" \
  "tree (64 MiB a call): commit fewer results or carry parts by hand" >&2; exit 2; }
echo "tree $((tree / 1048576)) MiB: $per part(s) of $((part / 1048576)) MiB a call"
[[ $per =~ ^[1-9][0-9]*$ ]] || { echo "pack_out: PER must be a positive whole number of parts, got $per" >&2; exit 2; }
rm -rf .device/$name.in*
parts=($(ls $src | grep '^pack\.part' | sort))
k=0
for ((i = 0; i < ${#parts[@]}; i += per)); do
  k=$((k + 1)); d=.device/$name.in$k
  mkdir -p $d
  [ $k -eq 1 ] && cp $src/pack.json $d/
  for f in "${parts[@]:i:per}"; do cp $src/$f $d/; done
  echo "call $k: carry [\"$d\"]  ($(du -sm $d | cut -f1) MB)  command: mkdir -p out/pack/$name && cp $d/* out/pack/$name/"
done
