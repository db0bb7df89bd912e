#!/usr/bin/env bash
# Installs a kinfly-fw package on a running drone over ssh and restarts the service: copies the
# .deb with scp, checks that the drone's architecture matches it, installs it with dpkg (sudo
# when the login is not root; the drone's edits to /etc/kinfly/kinfly-fw.toml are kept, it is a
# conffile), restarts kinfly-fw and prints its state.
#
# Usage: scripts/deploy.sh --host USER@DRONE [--deb FILE.deb]
#   default --deb: the newest build-aarch64/pkg/kinfly-fw_*_arm64.deb (make package-aarch64)
#   KINFLY_SSH_OPTS: extra options for ssh and scp, e.g. "-i ~/.ssh/drone -o Port=2222"
set -euo pipefail

repo_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

die() { echo "deploy: error: $*" >&2; exit 1; }

main() {
  local host="" deb=""
  while (($#)); do
    case "$1" in
      --host) host="${2:-}"; shift 2 ;;
      --deb) deb="${2:-}"; shift 2 ;;
      -h | --help) sed -n '2,10p' "${BASH_SOURCE[0]}"; exit 0 ;;
      *) echo "deploy: unknown argument '$1'" >&2; exit 2 ;;
    esac
  done
  [[ -n "$host" ]] || die "give the drone as --host USER@DRONE (make deploy HOST=user@drone)"
  if [[ -z "$deb" ]]; then
    deb="$(ls -t "$repo_root"/build-aarch64/pkg/kinfly-fw_*_arm64.deb 2>/dev/null | head -n 1)"
    [[ -n "$deb" ]] || die "no package in build-aarch64/pkg: run make package-aarch64"
  fi
  [[ -f "$deb" ]] || die "$deb is not a file"
  local arch
  arch="$(dpkg-deb --field "$deb" Architecture)"

  # shellcheck disable=SC2206  # word splitting of the user's options is intended
  local ssh_opts=(-o BatchMode=yes ${KINFLY_SSH_OPTS:-})
  local remote_deb="/tmp/$(basename "$deb")"
  echo "deploy: $(basename "$deb") -> $host"
  scp -q "${ssh_opts[@]}" "$deb" "$host:$remote_deb"
  # One remote shell: the checks, the install and the restart succeed or fail together, and the
  # copy is removed either way.
  ssh "${ssh_opts[@]}" "$host" sh -s -- "$remote_deb" "$arch" <<'REMOTE'
set -eu
deb="$1" want="$2"
trap 'rm -f "$deb"' EXIT
sudo=""
[ "$(id -u)" = 0 ] || sudo="sudo -n"
have="$(dpkg --print-architecture)"
[ "$have" = "$want" ] || { echo "deploy: the drone is $have, the package is $want" >&2; exit 1; }
$sudo dpkg --install --force-confold "$deb"
$sudo systemctl restart kinfly-fw.service
sleep 1
systemctl --no-pager --lines=5 status kinfly-fw.service || true
REMOTE
  echo "deploy: installed; follow the log with: ssh $host journalctl -fu kinfly-fw"
}

main "$@"
