#!/usr/bin/env bash
# The system packages Rerun's viewer needs to draw without a display or GPU (overtake-render,
# scripts/readme-pictures.sh, tests/viz/test_views.py): Xvfb and Mesa's software Vulkan (lavapipe).
# Installs them with apt-get where they are missing and this runs as root or with sudo;
# otherwise says what to install and exits 0 (the test that needs them then skips, saying why).
set -euo pipefail
have() { command -v xvfb-run >/dev/null && compgen -G "/usr/share/vulkan/icd.d/lvp_icd*.json" >/dev/null; }
have && exit 0
packages=(xvfb mesa-vulkan-drivers)
if command -v apt-get >/dev/null; then
  sudo=""
  [[ "$(id -u)" != 0 ]] && command -v sudo >/dev/null && sudo="sudo -n"
  if [[ "$(id -u)" == 0 || -n "$sudo" ]]; then
    if $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends \
        "${packages[@]}" >/dev/null 2>&1 \
      || { $sudo apt-get update -q >/dev/null 2>&1 \
        && $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -q \
          --no-install-recommends "${packages[@]}" >/dev/null 2>&1; }; then
      have && exit 0
    fi
  fi
fi
echo "setup-viewer: Xvfb and Mesa's software Vulkan are missing and could not be installed here;" \
  "install them (Debian/Ubuntu: apt-get install ${packages[*]}) to draw recordings headless" >&2
exit 0
