#!/usr/bin/env bash
# The prepared device check (benchmarks/gpu_check.py): run on the device machine from the
# repository root, after benchmarks/gpu_check_prepare.sh filled .gpu_carry here:
#
#   bash benchmarks/gpu_check.sh            # logs in $OUT/gpu_check (or /tmp/gpu_check)
#
# with the device tool: run(command="bash benchmarks/gpu_check.sh", carry=[".gpu_carry"], timeout_s=420).
# The machine has torch, torchvision, timm, numpy, scipy, pillow, h5py and pytest; the wheels
# in .gpu_carry/wheels bring what else the steps import, and .gpu_carry/datasets the
# GardensPoint images. Arguments are passed on to gpu_check.py.
set -uo pipefail
cd "$(dirname "$0")/.."
carry=${VPR_GPU_CARRY:-.gpu_carry}
site=/tmp/vpr_gpu_site
if compgen -G "$carry/wheels/*.whl" >/dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$site" \
        "$carry"/wheels/*.whl || exit 1
    export PYTHONPATH="$site"
fi
export PYTHONPATH="$PWD:$PWD/benchmarks${PYTHONPATH:+:$PYTHONPATH}"
export VPR_EXPLORER_DATA=${VPR_EXPLORER_DATA:-$PWD/$carry/datasets}
export VPR_EXPLORER_CACHE=${VPR_EXPLORER_CACHE:-/tmp/vpr_gpu_cache}
export PYTHONUNBUFFERED=1
logs=${OUT:-/tmp}/gpu_check
# 6 minutes for everything: gpu_check.py's own budget is 330 s, the rest is installing and margin.
timeout 360 python3 benchmarks/gpu_check.py --logs "$logs" "$@"
