#!/usr/bin/env bash
# Pack warp-lang and bitsandbytes for the GPU machine (Python 3.12, CUDA 13) into .whl/site.part.*
# (each under the 64 MiB a call may carry). See scripts/gpu_bench.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p .whl && cd .whl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_24_x86_64 --platform manylinux_2_17_x86_64 \
  -d . warp-lang==1.19.0 bitsandbytes==0.50.2
rm -rf site && mkdir site
(cd site && for w in ../warp_lang-*.whl ../bitsandbytes-*.whl; do unzip -q "$w"; done
 rm -rf warp/examples warp/tests
 find bitsandbytes -name 'libbitsandbytes_*.so' ! -name '*cuda130*' ! -name '*cpu*' -delete)
tar -cf - -C site . | xz -T0 -6 > site.tar.xz
rm -f site.part.* && split -b 53m site.tar.xz site.part.
rm -rf site site.tar.xz
ls -la site.part.*
