#!/usr/bin/env bash
# Installs what kinfly needs on Debian 12, one group of packages per kind of make target, so that
# `make demo` waits for a compiler and a few libraries, not for cross compilers, qemu or GRUB.
#
# Idempotent and fast when everything is present: apt is touched only when dpkg says a package
# is missing, pip only when a requirements file changed since the last successful install, and
# the ground package (ground/) is rebuilt only when a file it is built from changed.
#
# Usage: scripts/install-deps.sh GROUP...      (--help lists the groups and their packages)

# The package lists below are read by name, which shellcheck cannot follow.
# shellcheck disable=SC2034
set -euo pipefail

repo_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

# The Debian packages of each group; a group also installs the groups it includes
# (group_includes below). Each package sits beside the code that uses it, so moving or dropping
# one is a local decision. The lists are read by name ("${group}_packages").

# cxx (in demo and unit): configuring and compiling the C++ project without its tests: kinfly-fw
# and the link tools (scripts/demo.py runs kinfly-fw and kinfly-keygen), kinfly-fuse, and the
# ground package's native module, which builds shared/ again (ground/CMakeLists.txt). gcc's
# OpenMP (libgomp) comes with g++.
cxx_packages=(
  g++ make cmake ninja-build pkg-config
  # shared/ and its tools (cmake/KinflyDependencies.cmake, shared/CMakeLists.txt)
  libeigen3-dev libpng-dev libzstd-dev libcli11-dev
  # proto/ (lcm-gen: cmake/FindLCM.cmake) and firmware/link/ (signing; erasure coding of keyframe
  # chunks); liblcm-bin also has the lcm-logger that records the demo's flight
  liblcm-dev liblcm-bin libsodium-dev libcm256cc-dev
  # firmware/sources/ and app/ (kinfly-fw): logging, the OpenNI2 sensor source and libusb for
  # its hot-plug;
  # tests/tools/oni/ (the OpenNI2 test driver) finds the same OpenNI2
  libspdlog-dev libopenni2-dev libusb-1.0-0-dev
  # the C++ build's Python (.venv-build): pymavlink's mavgen makes the firmware's MAVLink headers
  python3 python3-venv
)

# demo (make demo, make eval): the Python environment .venv with the ground package (python3-dev
# for its native module), and `ip` for the demo's network namespace (scripts/netns.py).
demo_packages=(
  python3 python3-venv python3-dev iproute2
)

# sim (make sim; in unit, since the simulator's unit tests build with the others): the ray
# tracer that renders the simulated depth camera, the TOML reader of its missions, the mesh
# reader of its scenes from files and Boost.Random's normal deviates (sim/CMakeLists.txt)
sim_packages=(
  libembree-dev libtomlplusplus-dev libcgal-dev libboost-dev
)

# unit (make test-asan, and the unit tests of make test): GoogleTest (CMake's
# KINFLY_BUILD_TESTS). No gmock: nothing uses it, and GTestConfig.cmake includes its targets only
# if present. No Google Benchmark: the benchmarks (tests/bench) are Python over the programs.
unit_packages=(
  libgtest-dev
)

# test (make test): what the integration tests use beyond demo and unit.
test_packages=(
  # tests/packaging/test_flash.py: sfdisk and mkfs.ext4 on loop devices (losetup, partx and
  # mount come with every Debian system)
  fdisk e2fsprogs
  # tests/ground/test_viewer_screenshot.py: the rerun viewer on a virtual X display with
  # software Vulkan (Mesa's lavapipe), the X libraries it loads at run time, and the certificates
  # rerun's control client loads even for http to 127.0.0.1
  xvfb libvulkan1 mesa-vulkan-drivers libxcursor1 libxi6 libxkbcommon-x11-0 ca-certificates
  # tests/system/test_link_shape.py: nft for the Wi-Fi-like link's packet loss
  # (scripts/netns.py, LinkShape; its cap is tc, from iproute2)
  nftables
)

# fuzz (make fuzz): clang with libFuzzer, and clang's OpenMP runtime (the project configures
# whole, with the unit tests, so fuzz includes unit).
fuzz_packages=(
  clang libclang-rt-14-dev libomp-14-dev
)

# aarch64 (make firmware-aarch64, make package-aarch64): the cross compiler, qemu-user for the
# arm64 unit tests (the toolchain file's emulator), mmdebstrap and Debian's keyring for the sysroot
# (scripts/aarch64-sysroot.sh); CMake, Ninja, pkg-config and lcm-gen of the build host. The arm64
# libraries come from the sysroot, not from here.
aarch64_packages=(
  cmake ninja-build pkg-config liblcm-bin
  g++-aarch64-linux-gnu qemu-user mmdebstrap debian-archive-keyring
  # .venv-build on the build machine, as for the native build (mavgen)
  python3 python3-venv
)

# image (make image: scripts/build-image.sh): qemu-user-static with binfmt-support and arch-test
# for the image's maintainer scripts, and the tools that assemble the disk image from files (no
# mounts): sfdisk, mkfs.vfat, mcopy, mkfs.ext4, grub-mkimage.
image_packages=(
  qemu-user-static binfmt-support arch-test
  dosfstools mtools fdisk e2fsprogs grub-common
  # the uefi image booted in a test (tests/packaging/test_image.py): a virt board, UEFI firmware;
  # the rpi4 image read: its initramfs unpacked and listed, its device trees' properties
  qemu-system-arm qemu-efi-aarch64 zstd cpio device-tree-compiler
)

# bench (make bench): callgrind for the drone's instructions per frame
# (tests/bench/bench_onboard.py), nft for the lossy links of tests/bench/bench_link.py
# (scripts/netns.py); the group also makes .venv-bench (Open3D, RotorPy).
bench_packages=(
  valgrind nftables
)

all_groups=(demo sim unit test fuzz aarch64 image bench)

# The groups that GROUP includes.
group_includes() {
  case "$1" in
    demo | sim) echo cxx ;;
    unit) echo cxx sim ;;
    test) echo demo unit ;;
    fuzz) echo unit ;;
    image) echo aarch64 ;;
    bench) echo demo sim ;;
  esac
}

usage() {
  cat <<'EOF'
Usage: scripts/install-deps.sh GROUP...

Installs the Debian packages of each GROUP (apt-get, with sudo when not root, only for packages
dpkg reports missing) and the Python environments the group needs. Each make target names the
groups it uses:

  demo     make demo, make eval: the C++ build of the programs, Python with its headers, `ip`;
           .venv from requirements.txt with the ground package (ground/)
  sim      make sim: the C++ build, Embree (kinfly-sim's depth camera), toml++ (its
           missions) and CGAL (its scenes from mesh files)
  unit     make test-asan: the C++ build, the sim group and GoogleTest
           (every group that compiles, aarch64 too, makes .venv-build from
           requirements-build.txt: pymavlink's mavgen for the firmware's MAVLink headers)
  test     make test: demo + unit + what the integration tests use (nft for the
           Wi-Fi-like link)
  fuzz     make fuzz: unit + clang with libFuzzer
  aarch64  make firmware-aarch64, make package-aarch64: cross compiler, qemu-user, mmdebstrap
  image    make image: aarch64 + qemu-user-static, binfmt-support and the disk image tools
           (make test-aarch64 installs demo, unit and image)
  bench    make bench: demo + sim + valgrind, nft; .venv-bench from requirements-bench.txt
           (Open3D)
  all      every group above (make deps)

The Debian packages each group adds to those it includes:
EOF
  local group includes own
  for group in cxx "${all_groups[@]}"; do
    own="${group}_packages[*]"
    includes="$(group_includes "$group")"
    printf '%s\n' "${includes:+${includes// / + } + }${!own}" |
      fold -s -w 88 | sed "s/ *$//; 1s/^/  $(printf '%-8s' "$group") /; 2,\$s/^/           /"
  done
  echo "  (cxx: the compiler and the libraries kinfly-fw links, shared by demo and unit)"
}

log() { echo "[install-deps] $*"; }

# Appends GROUP and the groups it includes, those first, to the global `groups`, each once
# (the global associative array `seen` holds the groups appended so far).
declare -a groups=()
declare -A seen=()
add_group() {
  local group="$1" included
  [[ -z "${seen[$group]:-}" ]] || return 0
  seen[$group]=1
  for included in $(group_includes "$group"); do
    add_group "$included"
  done
  groups+=("$group")
}

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
  mapfile -t missing < <(missing_apt_packages "$@" | sort -u)
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
  want="$(cat "$requirements" "$repo_root/requirements.txt" "$repo_root/requirements-build.txt" |
          sha256sum | cut -d' ' -f1)"
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
# native module over shared/ and firmware/link) is reinstalled into VENV whenever a file it is
# built from changes.
ensure_ground_package() {
  local venv="$1"
  local stamp="$venv/.ground.sha256"
  local want
  want="$(cd "$repo_root" && find ground proto cmake shared firmware/link -type f \
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
  (($#)) || { usage >&2; exit 2; }
  local arg
  for arg in "$@"; do
    case "$arg" in
      -h | --help) usage; exit 0 ;;
      all) set -- "${all_groups[@]}"; break ;;
    esac
  done
  for arg in "$@"; do
    if [[ " ${all_groups[*]} " != *" $arg "* ]]; then
      echo "install-deps.sh: unknown group '$arg' (--help lists them)" >&2
      exit 2
    fi
    add_group "$arg"
  done

  local packages=() group own
  for group in "${groups[@]}"; do
    own="${group}_packages[@]"
    packages+=("${!own}")
  done
  install_apt_packages "${packages[@]}"

  if [[ -n "${seen[cxx]:-}" || -n "${seen[aarch64]:-}" ]]; then
    ensure_venv "$repo_root/.venv-build" "$repo_root/requirements-build.txt"
  fi
  if [[ -n "${seen[demo]:-}" ]]; then
    ensure_venv "$repo_root/.venv" "$repo_root/requirements.txt"
    ensure_ground_package "$repo_root/.venv"
  fi
  if [[ -n "${seen[bench]:-}" ]]; then
    # The benchmarks evaluate with the ground station's own ATE (kinfly_ground.outputs).
    ensure_venv "$repo_root/.venv-bench" "$repo_root/requirements-bench.txt"
    ensure_ground_package "$repo_root/.venv-bench"
  fi
}

main "$@"
