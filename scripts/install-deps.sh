#!/usr/bin/env bash
# Installs what kinfly needs on Debian 12: the C++ toolchain and libraries from apt, and the
# Python environment (.venv) from requirements.txt.
#
# Idempotent and fast when everything is present: apt is touched only when dpkg says a package
# is missing, and pip only when requirements.txt changed since the last successful install.
#
# Usage: scripts/install-deps.sh [--bench]
#   --bench  also (re)creates .venv-bench from requirements-bench.txt (Open3D, benchmark only)
set -euo pipefail

repo_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

apt_packages=(
  build-essential cmake ninja-build pkg-config
  libeigen3-dev libpng-dev
  libgtest-dev libgmock-dev libbenchmark-dev libcli11-dev libspdlog-dev libzstd-dev
  # make fuzz: clang with libFuzzer, and clang's OpenMP runtime (the project configures whole)
  clang libclang-rt-14-dev libomp-14-dev
  python3 python3-venv python3-dev
  liblcm-dev liblcm-bin libsodium-dev libzstd-dev iproute2
  # kinfly-fw's depth sensors: OpenNI2 (with its PS1080 and file drivers) and libusb for hot-plug
  libopenni2-dev libusb-1.0-0-dev
  # make firmware-aarch64 / image: the cross compiler, qemu-user for the arm64 tests, the sysroot
  # and image builder, qemu-user-static with binfmt-support for the image's maintainer scripts,
  # and the tools that assemble the disk image from files (no mounts)
  g++-aarch64-linux-gnu qemu-user mmdebstrap arch-test debian-archive-keyring
  qemu-user-static binfmt-support dosfstools mtools fdisk e2fsprogs grub-common
)

log() { echo "[install-deps] $*"; }

# Prints the packages of "$@" that dpkg does not report as fully installed.
missing_apt_packages() {
  local pkg status
  for pkg in "$@"; do
    status="$(dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null || true)"
    [[ "$status" == "install ok installed" ]] || echo "$pkg"
  done
}

install_apt_packages() {
  local missing
  mapfile -t missing < <(missing_apt_packages "${apt_packages[@]}")
  if ((${#missing[@]} == 0)); then
    log "apt packages: all present"
    return
  fi
  log "apt packages missing: ${missing[*]}"
  local sudo=()
  [[ "$(id -u)" == 0 ]] || sudo=(sudo)
  "${sudo[@]}" apt-get update
  # env, not a plain assignment: sudo resets the environment.
  "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive \
    apt-get install -y --no-install-recommends "${missing[@]}"
}

# The system interpreter is preferred so that .venv matches what a fresh Debian 12 has, whatever
# pyenv or conda shims sit first on PATH.
pick_python() {
  if [[ -x /usr/bin/python3 ]]; then echo /usr/bin/python3; else command -v python3; fi
}

# ensure_venv DIR REQUIREMENTS: creates DIR and installs REQUIREMENTS into it, skipping pip when
# the stamp inside DIR records the same requirements hash (a half-failed install leaves no stamp).
ensure_venv() {
  local venv="$1" requirements="$2"
  local stamp="$venv/.requirements.sha256"
  local want
  want="$(cat "$requirements" "$repo_root/requirements.txt" | sha256sum | cut -d' ' -f1)"
  if [[ -x "$venv/bin/python" && -f "$stamp" && "$(cat "$stamp")" == "$want" ]]; then
    log "$(basename "$venv"): up to date"
    return
  fi
  if [[ ! -x "$venv/bin/python" ]]; then
    log "creating $(basename "$venv")"
    "$(pick_python)" -m venv "$venv"
  fi
  log "installing $(basename "$requirements") into $(basename "$venv")"
  "$venv/bin/python" -m pip install --disable-pip-version-check -q --upgrade pip
  "$venv/bin/python" -m pip install --disable-pip-version-check -q -r "$requirements"
  echo "$want" >"$stamp"
}

# The ground package (ground/, built by scikit-build-core: lcm-gen for the Python messages and the
# native module over shared/) is reinstalled into VENV whenever a file it is built from changes.
ensure_ground_package() {
  local venv="$1"
  local stamp="$venv/.ground.sha256"
  local want
  want="$(cd "$repo_root" && find ground proto cmake shared -type f \
            -not -path '*/__pycache__/*' -not -name '*.pyc' -print0 |
          sort -z | xargs -0 sha256sum | sha256sum | cut -d' ' -f1)"
  if [[ -f "$stamp" && "$(cat "$stamp")" == "$want" ]]; then
    log "kinfly-ground package: up to date"
    return
  fi
  log "installing the kinfly-ground package (ground/) into $(basename "$venv")"
  "$venv/bin/python" -m pip install --disable-pip-version-check -q --no-deps "$repo_root/ground"
  echo "$want" >"$stamp"
}

main() {
  local bench=0
  for arg in "$@"; do
    case "$arg" in
      --bench) bench=1 ;;
      -h | --help) sed -n '2,10p' "${BASH_SOURCE[0]}"; exit 0 ;;
      *) echo "install-deps.sh: unknown argument '$arg'" >&2; exit 2 ;;
    esac
  done
  install_apt_packages
  ensure_venv "$repo_root/.venv" "$repo_root/requirements.txt"
  ensure_ground_package "$repo_root/.venv"
  if ((bench)); then
    # The benchmarks evaluate with the ground station's own ATE (kinfly_ground.outputs).
    ensure_venv "$repo_root/.venv-bench" "$repo_root/requirements-bench.txt"
    ensure_ground_package "$repo_root/.venv-bench"
  fi
}

main "$@"
