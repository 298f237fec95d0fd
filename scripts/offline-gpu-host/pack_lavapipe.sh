#!/usr/bin/env bash
# Mesa's lavapipe (the Vulkan driver that renders on the CPU), as installed here by `make setup`, with the
# libraries it loads, into .gpu/lavapipe.tar.xz for gpu_onebox.sh: `setup` unpacks it into $SITE/lavapipe
# and keeps only the libraries the GPU host lacks; RVT2_VULKAN=lavapipe then renders with it.
#
# Why carry it to a GPU machine: the simulator rebuilds its scene at every episode, and with NVIDIA's driver
# each rebuild allocates and frees GPU memory (render targets, and their CUDA mappings) under the driver's
# one lock. Sixty recording workers on 4 x H200 spent most of their time waiting for it (docs/BENCHMARKS.md,
# "Recording"); with lavapipe a worker's rendering is its own core's work.
set -euo pipefail
cd "$(dirname "$0")/../.."
manifest=$(ls /usr/share/vulkan/icd.d/lvp_icd*.json 2>/dev/null | head -1)
[ -n "$manifest" ] || { echo "pack_lavapipe: no lavapipe installed here (/usr/share/vulkan/icd.d/lvp_icd*.json); run make setup" >&2; exit 1; }
library=$(python3 -c "import json, sys; print(json.load(open(sys.argv[1]))['ICD']['library_path'])" "$manifest")
case $library in /*) ;; *) library=$(ldconfig -p | awk -v n="$library" '$1 == n {print $NF; exit}') ;; esac
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$work/lib"
cp -L "$library" "$work/lib/libvulkan_lvp.so"
cp "$manifest" "$work/lvp_icd.json"
# its libraries, less the C and C++ runtimes (a host has them, newer, and they must not be shadowed)
ldd "$library" | awk '$3 ~ /^\// {print $3}' | while read -r dependency; do
  case $(basename "$dependency") in
    libc.so*|libm.so*|libpthread.so*|libdl.so*|librt.so*|libgcc_s.so*|libstdc++.so*|ld-linux*) ;;
    *) cp -L "$dependency" "$work/lib/" ;;
  esac
done
mkdir -p .gpu
tar -cf - -C "$work" . | xz -T2 -9 > .gpu/lavapipe.tar.xz
ls -la .gpu/lavapipe.tar.xz
tar -tJf .gpu/lavapipe.tar.xz | sed -n '1,40p'
