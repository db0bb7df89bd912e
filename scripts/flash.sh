#!/usr/bin/env bash
# Writes a kinfly disk image to an SD card or USB disk, refusing anything that could be a disk this
# computer needs: a path that is not a block device, a partition, a device that is mounted (or
# has a mounted partition, or is held by LVM/RAID/dm-crypt), a non-removable disk, a device smaller
# than the image, and any run without --yes.
#
# Usage: scripts/flash.sh --image IMAGE --device /dev/sdX [--yes] [--dry-run]
#   --yes      confirms that everything on the device may be overwritten (make flash: CONFIRM=yes)
#   --dry-run  every check, then print the write instead of doing it
#
# KINFLY_SYSFS (default /sys) is where block devices are looked up; the tests point it at a copy
# to present a removable device.
set -euo pipefail

sysfs="${KINFLY_SYSFS:-/sys}"

die() { echo "flash: refused: $*" >&2; exit 1; }

# The "major:minor" of every mounted file system and active swap device.
mounted_devices() {
  awk '{ print $3 }' /proc/self/mountinfo
  local swap
  while read -r swap _; do
    [[ -b "$swap" ]] && printf '%d:%d\n' "0x$(stat -L -c %t "$swap")" "0x$(stat -L -c %T "$swap")"
  done < <(tail -n +2 /proc/swaps)
}

main() {
  local image="" device="" yes=0 dry_run=0
  while (($#)); do
    case "$1" in
      --image) image="${2:-}"; shift 2 ;;
      --device) device="${2:-}"; shift 2 ;;
      --yes) yes=1; shift ;;
      --dry-run) dry_run=1; shift ;;
      -h | --help) sed -n '2,12p' "${BASH_SOURCE[0]}"; exit 0 ;;
      *) echo "flash: unknown argument '$1'" >&2; exit 2 ;;
    esac
  done
  [[ -n "$image" && -n "$device" ]] || { sed -n '7,9p' "${BASH_SOURCE[0]}" >&2; exit 2; }
  [[ -f "$image" ]] || die "image $image is not a file (make image builds one)"

  # Symlinks such as /dev/disk/by-id/usb-... are fine; what they point at is checked.
  local real
  real="$(realpath -e "$device" 2>/dev/null)" || die "$device does not exist"
  [[ -b "$real" ]] || die "$device is not a block device"
  local name
  name="$(basename "$real")"
  local block="$sysfs/class/block/$name"
  [[ -d "$block" ]] || die "$device ($name) is not in $sysfs/class/block"
  [[ ! -e "$block/partition" ]] || die "$device is a partition: give the whole disk"

  # The disk and each of its partitions, as major:minor, against what is mounted.
  local mounted part dev
  mounted="$(mounted_devices)"
  for part in "$block" "$block/$name"*; do
    [[ -f "$part/dev" ]] || continue
    dev="$(cat "$part/dev")"
    if grep -qxF "$dev" <<<"$mounted"; then
      die "$(basename "$part") is mounted (or used as swap): unmount it first"
    fi
    if [[ -d "$part/holders" ]] && [[ -n "$(ls -A "$part/holders")" ]]; then
      die "$(basename "$part") is in use by $(ls "$part/holders" | tr '\n' ' ')" \
          "(LVM, RAID, dm-crypt)"
    fi
  done

  [[ "$(cat "$block/removable" 2>/dev/null || echo 0)" == 1 ]] ||
    die "$device is not a removable disk ($block/removable is not 1): an SD card or USB" \
        "stick is expected"

  local device_bytes image_bytes
  device_bytes=$(( $(cat "$block/size") * 512 ))
  image_bytes="$(stat -c %s "$image")"
  ((device_bytes >= image_bytes)) ||
    die "$device holds $((device_bytes / 1048576)) MiB," \
        "the image needs $((image_bytes / 1048576)) MiB"

  ((yes)) || die "this overwrites everything on $device ($((device_bytes / 1000000)) MB): add" \
                 "--yes (make flash ... CONFIRM=yes) to go ahead"

  local write=(dd "if=$image" "of=$real" bs=4M conv=fsync status=progress)
  if ((dry_run)); then
    echo "flash: would run: ${write[*]}"
    return
  fi
  echo "flash: writing $image to $device"
  "${write[@]}"
  sync
  # The kernel still has the old partition table in memory.
  blockdev --rereadpt "$real" 2>/dev/null || true
  echo "flash: done; edit kinfly.conf on the KINFLYBOOT partition before the first boot"
}

main "$@"
