#!/usr/bin/env bash
# System packages the simulator (SAPIEN on software Vulkan) and open3d need on Debian 12.
# Idempotent: does nothing when everything is already installed.
set -euo pipefail

need_pkgs=(libvulkan1 libusb-1.0-0 libgl1 libegl1 libglib2.0-0 libgomp1)
# A bare Debian python3 cannot make virtualenvs without python3-venv.
${PYTHON:-python3} -c 'import ensurepip' 2>/dev/null || need_pkgs+=(python3-venv)
backports_pkgs=(mesa-vulkan-drivers)

missing=()
for p in "${need_pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
# SAPIEN needs Mesa >= 23 lavapipe (descriptor indexing); bookworm ships 22.3, backports ships 25.x.
lvp_ver=$(dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null || true)
lvp_major=${lvp_ver%%.*}; lvp_major=${lvp_major#*:}
need_backports=0
if [ -z "$lvp_ver" ] || [ "${lvp_major:-0}" -lt 23 ]; then need_backports=1; fi

if [ ${#missing[@]} -eq 0 ] && [ $need_backports -eq 0 ]; then
  echo "system packages: already installed (mesa-vulkan-drivers $lvp_ver)"
  exit 0
fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  command -v sudo >/dev/null || { echo "setup: need root or sudo to install: ${missing[*]} ${backports_pkgs[*]}" >&2; exit 1; }
  SUDO=sudo
fi

if [ $need_backports -eq 1 ] && ! grep -rqs "bookworm-backports" /etc/apt/sources.list /etc/apt/sources.list.d/; then
  echo "setup: enabling bookworm-backports for mesa-vulkan-drivers 25.x"
  echo "deb http://deb.debian.org/debian bookworm-backports main" | $SUDO tee /etc/apt/sources.list.d/rvt2-bookworm-backports.list >/dev/null
fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
[ ${#missing[@]} -eq 0 ] || $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
if [ $need_backports -eq 1 ]; then
  $SUDO apt-get install -y -qq --no-install-recommends -t bookworm-backports "${backports_pkgs[@]}"
fi
echo "system packages: installed (mesa-vulkan-drivers $(dpkg-query -W -f='${Version}' mesa-vulkan-drivers))"
