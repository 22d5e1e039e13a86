#!/usr/bin/env bash
# A run's pack (out/pack/NAME: pack.json + 15 MiB parts, `arms_gpu.sh pack` / `rwwarp design pack`) laid out for the
# trip to a GPU machine: the device tool carries at most 64 MiB a call with the repository's tracked tree (~18 MB),
# so the parts go in folders .device/NAME.inK of at most PER parts each (default 3: 47 MB), pack.json in the first.
# Run from the repository root; then one call per folder, in order (the first may also start other work):
#   carry [".device/NAME.inK"], command: mkdir -p out/pack/NAME && cp .device/NAME.inK/* out/pack/NAME/
# and after the last one `bash perf/tools/arms_gpu.sh start ...` finds out/pack/NAME and resumes from it (it checks
# every part's sha256 against pack.json). A call that also carries data/debian-photos (12 MiB) takes at most 2 parts.
#   bash perf/tools/pack_out.sh NAME [PER]
set -euo pipefail
name=${1:?run name (a folder of out/pack)}; per=${2:-3}
src=out/pack/$name
[ -f $src/pack.json ] || { echo "pack_out: $src/pack.json not found" >&2; exit 2; }
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
