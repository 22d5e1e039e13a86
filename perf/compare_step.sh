#!/usr/bin/env bash
# One design step profiled at two commits on the same GPU machine (perf/profile_step.py: median step,
# device kernels + copies, device-busy fraction, peaks, Warp launches), the older from an archive:
#   git archive -o .bisect/base.tgz BASE            # here; .bisect/ is ignored, carried to the device
#   bash perf/compare_step.sh .bisect/base.tgz BASE [STEPS] [CONFIG]   # there, after rw-env.sh
# Writes $OUT/base/ and $OUT/new/ (profile_step_<config>_cuda.txt / .json).
set -u
tgz=$1; base=$2; steps=${3:-8}; config=${4:-cooke_hybrid}
out=${OUT:-perf/results}
here=$(cd "$(dirname "$0")/.." && pwd)
rm -rf /tmp/base_src /tmp/inst_base && mkdir -p /tmp/base_src "$out/base" "$out/new"
tar -xzf "$tgz" -C /tmp/base_src && python3 -m pip install -q --no-deps --no-build-isolation --target /tmp/inst_base /tmp/base_src >/dev/null 2>&1 \
  || { echo "could not install $base"; exit 1; }
cd /tmp
echo "== $config at $base (base)"
RWWARP_COMMIT=$base PYTHONPATH=/tmp/inst_base${PYTHONPATH:+:$PYTHONPATH} timeout 280 python3 "$here/perf/profile_step.py" --config "$config" --preset gpu \
  --device cuda --steps "$steps" --out "$out/base" 2>&1 | grep -v "use_ai2\|Warning\|arm = Arm\|warnings.warn" | head -14
for flag in "" --pack; do
  echo "== $config at ${RWWARP_COMMIT:-the working tree} (new $flag)"
  (cd "$here" && timeout 240 python3 perf/profile_step.py --config "$config" --preset gpu --device cuda --steps "$steps" \
    $flag --out "$out/new" 2>&1 | grep -v "use_ai2\|Warning\|arm = Arm\|warnings.warn" | head -14)
done
