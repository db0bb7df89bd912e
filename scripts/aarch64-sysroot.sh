#!/usr/bin/env bash
# Creates the Debian 12 arm64 sysroot the aarch64 build compiles against and runs its tests in
# (under qemu-aarch64 -L): the -dev packages below and what they depend on, extracted by
# mmdebstrap (--variant=extract: nothing is configured, so no arm64 code runs).
#
# Cached: DIR is kept while its stamp records the same package list and suite; any change to the
# list rebuilds it from scratch (a few seconds from a near mirror, ~150 MB).
#
# Usage: scripts/aarch64-sysroot.sh DIR
set -euo pipefail

repo_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/aarch64-common.sh
source "$repo_root/scripts/aarch64-common.sh"

# What kinfly-fw, the link tools and the unit tests link (and libgomp1, which no -dev package
# here pulls in: the cross compiler brings its own for linking, the sysroot's runs them). A new
# link dependency of the firmware goes here as its Debian -dev package.
sysroot_packages=(
  libc6-dev libgomp1
  libeigen3-dev libpng-dev libzstd-dev libsodium-dev libcm256cc-dev liblcm-dev libglib2.0-0
  libcli11-dev libspdlog-dev libfmt-dev
  libgtest-dev libgmock-dev
  libopenni2-dev libusb-1.0-0-dev
)

log() { echo "[aarch64-sysroot] $*"; }

main() {
  (($# == 1)) || { sed -n '2,9p' "${BASH_SOURCE[0]}" >&2; exit 2; }
  local dir="$1"
  local stamp="$dir/.kinfly-sysroot.sha256"
  local want
  local -a sources
  mapfile -t sources < <(kinfly_debian_sources main)
  # This script and its sources list: a changed package list or layout rebuilds the sysroot.
  want="$(cat "${BASH_SOURCE[0]}" "$repo_root/scripts/aarch64-common.sh" |
          cat - <(printf '%s\n' "${sources[@]}") | sha256sum | cut -d' ' -f1)"
  if [[ -f "$stamp" && "$(cat "$stamp")" == "$want" ]]; then
    log "$dir: up to date"
    return
  fi
  log "creating $dir (arm64, $KINFLY_DEBIAN_SUITE)"
  # Built beside the target and moved into place, so an interrupted run never leaves a sysroot
  # that looks complete.
  rm -rf "$dir" "$dir.tmp"
  mkdir -p "$(dirname "$dir")"
  local packages
  packages="$(IFS=,; echo "${sysroot_packages[*]}")"
  # Extracting keeps no dpkg database; the packages' shlibs files, saved while the .debs are still
  # there, are what the .deb's Depends are computed from (cmake/KinflyDebDepends.cmake).
  mmdebstrap --quiet --variant=extract --architectures=arm64 --include="$packages" \
    --extract-hook='for deb in "$1"/var/cache/apt/archives/*.deb; do
                      dpkg-deb --info "$deb" shlibs 2>/dev/null || true
                    done | grep -v "^udeb:" >"$1/.kinfly-shlibs"' \
    "$KINFLY_DEBIAN_SUITE" "$dir.tmp" "${sources[@]}"
  # Absolute symlinks inside the sysroot (e.g. lib*.so -> /lib/...) would point at the build
  # host's files; the linker and qemu need them relative to the sysroot.
  relativize_symlinks "$dir.tmp"
  echo "$want" >"$dir.tmp/.kinfly-sysroot.sha256"
  mv "$dir.tmp" "$dir"
  log "done: $(du -sh "$dir" | cut -f1)"
}

# relativize_symlinks ROOT: rewrites every absolute symlink under ROOT to point inside ROOT.
relativize_symlinks() {
  local root="$1" link target
  while IFS= read -r -d '' link; do
    target="$(readlink "$link")"
    [[ "$target" == /* ]] || continue
    ln -snf "$(realpath -m --relative-to="$(dirname "$link")" "$root$target")" "$link"
  done < <(find "$root" -type l -print0)
}

main "$@"
