#!/usr/bin/env bash
# Re-splits the GPU machine's staging folders (.device/w1..w3, written by the workplace's device-prepare hook) into
# four, so that each staging call's carry plus this repository's tracked tree stays under the device tool's 64 MiB
# a call: the Warp wheel in 4 parts of 37.5 MB (w1..w4), the small wheels, Debian packages, pyvkfft's source and
# the wheel's name in w4, which assembles and installs. Run from the repository root after device-prepare; then:
#   call N = 1, 2, 3: carry [".device/wN"], command `bash .device/wN/stage.sh N`
#   call 4:           carry [".device/w4"], command `bash .device/w4/stage.sh 4 && source $HOME/rw-env.sh && ...`
# (session 21: w1 was 51.2 MB, and with the 18 MB tree over the limit; after this 37.5 / 37.5 / 37.5 / 38.2 MB).
set -euo pipefail
cd .device
[ -f w1/warp.part00 ] && [ -f w2/warp.part01 ] && [ -f w3/warp.part02 ] || {
  echo "device_resplit: .device/w1..w3 with warp.part00..02 expected (run the device-prepare hook first)" >&2; exit 2; }
[ ! -e w4 ] || { echo "device_resplit: .device/w4 exists already: re-split once" >&2; exit 2; }
tmp=$(mktemp -d)
cat w1/warp.part00 w2/warp.part01 w3/warp.part02 > "$tmp/warp.whl"
split -b 37500000 -d -a 2 "$tmp/warp.whl" "$tmp/part."
n=$(ls "$tmp"/part.* | wc -l)
[ "$n" -eq 4 ] || { echo "device_resplit: the wheel split into $n parts, not 4" >&2; rm -rf "$tmp"; exit 1; }
mkdir w4
rm w1/warp.part00 w2/warp.part01 w3/warp.part02
for i in 0 1 2 3; do mv "$tmp/part.0$i" "w$((i + 1))/warp.part0$i"; done
mv w1/*.deb w1/*.whl w2/pyvkfft-src.tar.gz w3/warp-wheel-name w4/
# the stage script: step 4 (not 3) assembles, from four parts
sed -e 's/\[\[ \$step == 3 \]\]/[[ $step == 4 ]]/' \
    -e 's/warp\.part00 warp\.part01 warp\.part02;/warp.part00 warp.part01 warp.part02 warp.part03;/' \
    -e 's/warp\.part00 warp\.part01 warp\.part02 >/warp.part00 warp.part01 warp.part02 warp.part03 >/' \
    -e 's/make the three calls again/make the four calls again/' w1/stage.sh > "$tmp/stage.sh"
grep -q 'step == 4' "$tmp/stage.sh" && grep -q 'warp.part03 >' "$tmp/stage.sh" || {
  echo "device_resplit: the hook's stage.sh changed; edit it by hand" >&2; rm -rf "$tmp"; exit 1; }
for d in w1 w2 w3 w4; do cp "$tmp/stage.sh" "$d/stage.sh"; chmod +x "$d/stage.sh"; done
sha256sum "$tmp/warp.whl" | cut -c1-16
rm -rf "$tmp"
du -sb w1 w2 w3 w4
