#!/usr/bin/env bash
# Pack what rvt2 needs on a GPU machine without network access (Python 3.12, CUDA torch, numpy 2, nothing
# else installed) into .gpu/site.part.*, for gpu_onebox.sh. Run it from a machine with network access, in the
# repository. The host takes 64 MiB per transfer, the working tree included, so each piece is as large as the room the
# tree leaves (less 2 MiB for the commits before the run). `pack_gpu_wheels.sh --resplit` only cuts the pieces again
# to the tree of the day (seconds; the tree grows with every published run); `--room` prints that size in MiB.
#
# The simulator stack (SAPIEN, ManiSkill, mplib with numpy 1.26: mplib 0.1.1 crashes with numpy 2),
# the MCAP libraries, warp, scipy (the image's scipy wants numpy 2) and IPython (ManiSkill imports it), as
# wheels for cp312, unpacked into one folder and stripped of what rvt2 never loads (other robots' meshes,
# SAPIEN's headers, warp's examples and tests).
# The text encoder (88 MB) stays here: .gpu/embeddings.safetensors carries every task's instructions
# (scripts/embed_instructions.py, read through RVT2_EMBEDDINGS).
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PY:-.venv/bin/python}

room() {  # tree_mib and piece_mib: the MiB a piece may have beside today's working tree (weight pieces too)
  tree_mib=$(git ls-files -z --cached --others --exclude-standard | du -cb --files0-from=- 2>/dev/null |
    awk 'END {print int($1 / 1048576) + 1}')
  piece_mib=$(( 64 - tree_mib - 2 ))
  if [ "$piece_mib" -lt 4 ]; then
    echo "pack_gpu_wheels.sh: the working tree is ${tree_mib} MiB; a 64 MiB transfer has no room for a piece" >&2
    exit 1
  fi
}

split_site() {  # the compressed site on stdin -> .gpu/site.part.* sized to the transfer, and site.sha256
  room
  mkdir -p .gpu
  rm -f .gpu/site.part.*
  split -b "${piece_mib}m" - .gpu/site.part.
  (cd .gpu && sha256sum site.part.* > site.sha256)
  echo "site: $(ls .gpu/site.part.* | wc -l) pieces of ${piece_mib} MiB beside the ${tree_mib} MiB working tree"
}

if [ "${1:-}" = "--room" ]; then  # for gpu_checkpoint.py resplit
  room
  echo "$piece_mib"
  exit 0
fi
if [ "${1:-}" = "--resplit" ]; then
  if [ ! -f .gpu/site.sha256 ]; then
    echo "pack_gpu_wheels.sh --resplit: no .gpu/site.sha256 here; pack the site first (pack_gpu_wheels.sh)" >&2
    exit 1
  fi
  (cd .gpu && sha256sum --quiet -c site.sha256)
  whole=$(mktemp)
  trap 'rm -f "$whole"' EXIT
  cat .gpu/site.part.* > "$whole"
  split_site < "$whole"
  exit 0
fi
WHEELS=(
  mani-skill==3.0.1 sapien==3.0.3 mplib==0.1.1 numpy==1.26.4 toppra==0.6.10 transforms3d==0.4.2 trimesh==5.2.0
  gymnasium==1.4.0 Farama-Notifications==0.0.6 dacite==1.9.2 defusedxml==0.7.1 GitPython==3.2.1 gitdb==4.0.12
  smmap==5.0.3 tyro==1.0.17 docstring_parser==0.18.0 typeguard==4.6.0 pytorch-kinematics==0.7.6
  arm_pytorch_utilities==0.5.0 pytorch-seed==0.2.0 importlib_resources==7.1.0 pyperclip==1.11.0
  mcap==1.6.0 mcap-protobuf-support==0.6.0 foxglove-schemas-protobuf==0.4.0 zstandard==0.25.0
  rosbags==0.11.9 apsw==3.54.1.0 backports.zstd==1.8.0 ruamel.yaml==0.19.1 lz4==4.4.5
  jsonschema==4.26.0 fastjsonschema==2.22.3 jsonschema-specifications==2025.9.1 referencing==0.37.0 rpds-py==2026.9.1
  warp-lang==1.19.0 scipy==1.17.1 websockets==16.1.1 msgpack==1.2.4
  ipython==9.18.1 ipython_pygments_lexers==1.1.1 asttokens==3.0.2 decorator==5.3.1 executing==2.3.0 jedi==0.20.1
  matplotlib_inline==0.2.2 parso==0.8.7 pexpect==4.9.0 prompt_toolkit==3.0.53 ptyprocess==0.7.0 pure_eval==0.2.4
  stack_data==0.6.3 traitlets==5.16.1 wcwidth==0.9.4
)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
for wheel in "${WHEELS[@]}"; do
  $PY -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_24_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any \
    -d "$work/wheels" "$wheel" 2>/dev/null
done
mkdir "$work/site"
(cd "$work/site" && for w in ../wheels/*.whl; do unzip -q -o "$w"; done
 find mani_skill/assets/robots -mindepth 1 -maxdepth 1 ! -name panda -exec rm -rf {} +
 find mani_skill/assets/robots/panda -mindepth 1 -maxdepth 1 -type d ! -name franka_description ! -name realsense2_description -exec rm -rf {} +
 rm -rf mani_skill/assets/environment_maps mani_skill/assets/*.glb
 find mani_skill/utils/scene_builder -mindepth 1 -maxdepth 1 -type d ! -name table -exec sh -c 'find "$0" -type f ! -name "*.py" -delete' {} \;
 rm -rf sapien/include warp/examples warp/tests zstandard/_cffi*.so
 find . -name __pycache__ -type d -exec rm -rf {} +)
$PY scripts/embed_instructions.py --out "$work/site/embeddings.safetensors"
tar -cf - -C "$work/site" . | xz -T2 -9 | split_site
# The Vulkan and GL loaders as Debian packages: a GPU image may have NVIDIA's driver and no loader
# (`rvt2 doctor`: "failed to find a rendering device"); `gpu_onebox.sh setup` unpacks .gl/*.deb.
mkdir -p .gl /tmp/rvt2-apt-lists/partial
apt_options=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/rvt2-apt-lists)
apt-get "${apt_options[@]}" update -qq
(cd .gl && apt-get "${apt_options[@]}" download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
ls -la .gl
# Mesa's lavapipe for experiment files that render on the CPU (renderer = "lavapipe")
bash scripts/offline-gpu-host/pack_lavapipe.sh
