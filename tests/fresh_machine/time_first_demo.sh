#!/usr/bin/env bash
# Times the first `make demo` on a fresh Debian 12 machine, split into download, build and flight,
# by making one: a Debian 12 root built by mmdebstrap, the repository cloned into it, `make demo`
# run inside as root (the demo's network namespace needs root), then a second `make demo` for the
# cost of a run with everything in place.
#
# "Fresh Debian 12" here: minbase (the essential packages and apt) plus git (to clone the
# repository), make (to type `make demo`) and ca-certificates, from the same mirrors as the arm64
# sysroot (scripts/aarch64-common.sh). A real installation has more (a "standard system
# utilities" install has python3, iproute2 and some of their libraries), so the download figure
# is an upper bound. What is measured is the committed HEAD of this repository (or --rev), not
# uncommitted changes.
#
# Phases, from the timestamped output of `make demo`:
#   download  from the start to the ground package's build: apt-get update, download and unpack
#             of the demo group's packages, .venv and pip's downloads and installs
#   build     the ground package (ground/, pip --no-deps: its native module and messages; pip
#             fetches its two build requirements, scikit-build-core and nanobind, here) and the
#             CMake configure and build of kinfly-fw and kinfly-keygen
#   flight    scripts/demo.py: the key, the network namespace, the flight, the ground's outputs
#
# A machine whose TLS traffic passes a proxy with its own CA (as some sandboxes and companies do)
# gets the CAs from /usr/local/share/ca-certificates copied into the root, and pip is pointed at
# the system bundle; both are said when they happen.
#
# Needs root, mmdebstrap, unshare and the network (Debian's mirror and PyPI); about 2 GB in the
# root's folder. The root is removed at the end unless --keep.
#
# Usage: sudo tests/fresh_machine/time_first_demo.sh [--root DIR] [--rev REV] [--log FILE] [--keep]
set -euo pipefail

repo_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
# shellcheck source=scripts/aarch64-common.sh
source "$repo_root/scripts/aarch64-common.sh"

log() { echo "[time-first-demo] $*"; }
die() { echo "time_first_demo: error: $*" >&2; exit 1; }

# Microseconds since the epoch (bash 5; EPOCHREALTIME has six decimals).
now_us() { local t="$EPOCHREALTIME"; echo "${t/./}"; }

# Seconds with one decimal from microseconds.
seconds() { printf '%d.%d' "$(($1 / 1000000))" "$(($1 / 100000 % 10))"; }

# Prefixes every line of stdin with the seconds since START_US.
stamp_lines() {
  local start_us="$1" line
  while IFS= read -r line; do
    printf '%8s %s\n' "$(seconds "$(($(now_us) - start_us))")" "$line"
  done
}

# The time in microseconds (from the first column of the stamped log FILE) of the first line
# matching PATTERN.
time_of() {
  awk -v pattern="$2" '$0 ~ pattern { printf "%d\n", $1 * 1000000; exit }' "$1"
}

# Runs COMMAND in the root as root from the repository, with /proc, /sys, /dev and a fresh /run
# (where `ip netns` keeps its namespaces) mounted in a private mount namespace, so nothing stays
# mounted when it ends, whatever happens. The root is bound onto itself first: `ip netns exec`
# makes / a slave mount, which fails (EINVAL) where / is not a mount point.
in_root() {
  local root="$1" command="$2"
  local env=(PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin HOME=/root
             LANG=C.UTF-8 TERM=dumb)
  [[ -z "$pip_cert" ]] || env+=(PIP_CERT="$pip_cert")
  # shellcheck disable=SC2016  # expanded by the inner shell, from its arguments
  unshare --mount --propagation private -- bash -euo pipefail -c '
    root="$1"; shift
    mount --bind "$root" "$root"
    mount -t proc proc "$root/proc"
    mount -t sysfs sysfs "$root/sys"
    mount --rbind /dev "$root/dev"
    mount -t tmpfs tmpfs "$root/dev/shm"
    mount -t tmpfs tmpfs "$root/run"
    exec chroot "$root" env -i "$@"' bash "$root" "${env[@]}" \
      bash -euo pipefail -c "cd /root/kinfly && $command"
}

# Globals: the EXIT trap reads root and keep; in_root reads pip_cert.
root=""
keep=0
pip_cert=""

cleanup() {
  [[ -n "$root" && -d "$root" ]] || return 0
  ((keep)) && { log "kept $root"; return; }
  # The mounts lived in unshare's namespace only; refuse to delete through one regardless.
  if findmnt -rn -o TARGET | grep -qF "$root/"; then
    echo "time_first_demo: $root still has mounts; not removing it" >&2
    return
  fi
  rm -rf --one-file-system "$root"
}

main() {
  local rev=HEAD logfile=""
  while (($#)); do
    case "$1" in
      --root) root="$2"; shift 2 ;;
      --rev) rev="$2"; shift 2 ;;
      --log) logfile="$2"; shift 2 ;;
      --keep) keep=1; shift ;;
      -h | --help) sed -n '2,29p' "${BASH_SOURCE[0]}"; exit 0 ;;
      *) echo "time_first_demo: unknown argument '$1'" >&2; exit 2 ;;
    esac
  done
  [[ "$(id -u)" == 0 ]] || die "run as root (the chroot, its mounts and the demo's namespace)"
  local tool
  for tool in mmdebstrap unshare chroot git findmnt; do
    command -v "$tool" >/dev/null || die "$tool is missing"
  done
  ((BASH_VERSINFO[0] >= 5)) || die "bash 5 is needed (EPOCHREALTIME)"
  local commit
  commit="$(git -C "$repo_root" rev-parse --verify "$rev^{commit}")" || die "no commit $rev"

  if [[ -z "$root" ]]; then
    root="$(mktemp -d /var/tmp/kinfly-fresh.XXXXXX)"
  fi
  [[ ! -e "$root/usr" ]] || die "$root already holds a system: give an empty or new folder"
  logfile="${logfile:-$root.log}"
  trap cleanup EXIT

  log "making a fresh Debian 12 ($KINFLY_DEBIAN_SUITE minbase + git make ca-certificates) in $root"
  local -a sources
  mapfile -t sources < <(kinfly_debian_sources main)
  mmdebstrap --quiet --variant=minbase --include=git,make,ca-certificates \
    "$KINFLY_DEBIAN_SUITE" "$root" "${sources[@]}"

  if compgen -G "/usr/local/share/ca-certificates/*.crt" >/dev/null; then
    log "this machine trusts extra CAs (/usr/local/share/ca-certificates): copied into the root," \
        "pip pointed at the system bundle"
    cp /usr/local/share/ca-certificates/*.crt "$root/usr/local/share/ca-certificates/"
    chroot "$root" update-ca-certificates >/dev/null
    pip_cert=/etc/ssl/certs/ca-certificates.crt
  fi

  log "cloning $repo_root at ${commit:0:12} into $root/root/kinfly"
  git clone --quiet --no-hardlinks "$repo_root" "$root/root/kinfly"
  git -C "$root/root/kinfly" checkout --quiet --detach "$commit"

  log "first make demo (log: $logfile)"
  local start_us end_us rc=0
  start_us="$(now_us)"
  in_root "$root" "make demo" 2>&1 | stamp_lines "$start_us" | tee "$logfile" || rc=$?
  end_us="$(now_us)"
  ((rc == 0)) || die "make demo failed (exit $rc); the log: $logfile"
  local total build_start flight_start
  total=$((end_us - start_us))
  build_start="$(time_of "$logfile" "installing the kinfly-ground package")"
  flight_start="$(time_of "$logfile" "scripts/demo.py --out")"
  [[ -n "$build_start" && -n "$flight_start" ]] ||
    die "the phase markers are not in $logfile (install-deps.sh or the Makefile changed?)"

  log "second make demo"
  local second_us
  second_us="$(now_us)"
  in_root "$root" "make demo" >"$logfile.second" 2>&1 ||
    die "the second make demo failed: $logfile.second"
  second_us=$(($(now_us) - second_us))

  local apt_fetched venv_size packages
  apt_fetched="$(grep -o 'Fetched .*' "$logfile" | tail -n 1 || true)"
  packages="$(grep -o '[0-9]* newly installed' "$logfile" | head -n 1 || true)"
  venv_size="$(du -sh "$root/root/kinfly/.venv" | cut -f1)"
  echo
  echo "first make demo on a fresh Debian 12 (commit ${commit:0:12}, $(nproc) cores):"
  printf '  download  %6s s   apt: %s (%s); .venv: %s\n' "$(seconds "$build_start")" \
    "${packages:-?}" "${apt_fetched:-?}" "$venv_size"
  printf '  build     %6s s   the ground package, kinfly-fw, kinfly-keygen\n' \
    "$(seconds $((flight_start - build_start)))"
  printf '  flight    %6s s   %s\n' "$(seconds $((total - flight_start)))" \
    "$(grep -o 'demo: done in [0-9]* s' "$logfile" | head -n 1 || true)"
  printf '  total     %6s s\n' "$(seconds "$total")"
  printf 'second make demo (everything in place): %s s\n' "$(seconds "$second_us")"
}

main "$@"
