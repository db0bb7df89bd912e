#!/usr/bin/env bash
# Builds the flashable arm64 disk images of a kinfly drone: Debian 12 minbase (mmdebstrap) with a
# kernel, Wi-Fi, ssh and chrony, the kinfly-fw package installed and enabled, and a first-boot
# unit that applies kinfly.conf from the FAT partition (Wi-Fi, vehicle id and key), one image per
# board asked for:
#   uefi  GRUB as the removable-media EFI loader: UEFI boards, U-Boot's EFI boot, qemu's virt board
#   rpi4  Raspberry Pi 4, 400 and CM4: Debian's raspi-firmware (the Pi's own boot firmware, from
#         non-free-firmware) loads the kernel, its initramfs and the board's device tree itself,
#         as config.txt and cmdline.txt say
# The Raspberry Pi 5 is not offered: Debian 12's raspi-firmware (1.20220830) predates it, and its
# kernel (6.1) has no device tree for the Pi 5's BCM2712.
#
# Every board's image has the same root file system (both boards' boot packages in it), so an
# image is the same whichever boards were built beside it; they differ in their FAT partition.
#
# Layout (MBR, which the Raspberry Pi's firmware needs):
#   p1  FAT32 "KINFLYBOOT", 256 MiB, /boot/firmware: the board's boot files (uefi:
#       EFI/BOOT/BOOTAA64.EFI + grub.cfg; rpi4: start4.elf, fixup4.dat, config.txt, cmdline.txt,
#       the kernel, its initramfs and the bcm*.dtb device trees), kinfly.conf (provisioning,
#       deleted once applied), kinfly.conf.example
#   p2  ext4 "kinfly-root", /: sized to its contents plus headroom, grown to the card at first boot
#
# The image is assembled from files (sfdisk on an image file, mkfs.vfat + mcopy, mkfs.ext4 -d, dd
# into place): nothing is mounted. mmdebstrap runs the packages' maintainer scripts (kernel
# initramfs, users, the kinfly-fw postinst) inside the arm64 tree, which needs qemu-user-static
# registered with binfmt_misc; this script registers it when it is not (root only).
#
# Usage: scripts/build-image.sh --deb kinfly-fw_VERSION_arm64.deb --image BOARD=IMAGE
#            [--image BOARD=IMAGE ...] [--work DIR]
set -euo pipefail

repo_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/aarch64-common.sh
source "$repo_root/scripts/aarch64-common.sh"

# Beyond minbase: boot (kernel, initramfs, udev; GRUB's arm64 modules for uefi; the Pi's firmware
# for rpi4, whose kernel hook keeps the FAT partition's copy of the kernel current through
# upgrades), the network (Wi-Fi with the regulatory database the kernel loads for wifi_country,
# the Pi 4's Wi-Fi chip's firmware, systemd-networkd, ssh for `make deploy`), time (the uplink's
# 2 s signing window needs NTP), and what the first boot uses to grow the root partition.
image_packages=(
  systemd-sysv udev kmod linux-image-arm64 grub-efi-arm64-bin raspi-firmware
  wpasupplicant wireless-regdb firmware-brcm80211 iproute2 openssh-server chrony
  fdisk dosfstools zstd
)
boot_mib=256
# Free space left in the root file system before the first boot grows it.
root_headroom_mib=256

log() { echo "[build-image] $*"; }
die() { echo "build-image: error: $*" >&2; exit 1; }

# mmdebstrap's own check: can this machine execute arm64 programs (through binfmt_misc)?
ensure_arm64_exec() {
  arch-test arm64 >/dev/null 2>&1 && return
  log "arm64 programs do not run here yet: registering qemu-aarch64 with binfmt_misc"
  [[ "$(id -u)" == 0 ]] || die "needs root to register qemu-user-static with binfmt_misc"
  update-binfmts --enable qemu-aarch64 >/dev/null 2>&1 || true
  arch-test arm64 >/dev/null 2>&1 ||
    die "arm64 programs cannot run on this machine (no binfmt_misc?): install qemu-user-static " \
        "and binfmt-support and check /proc/sys/fs/binfmt_misc/qemu-aarch64"
}

# Shell run by mmdebstrap once the essential packages are in, before the rest (the kernel) install.
essential_hook() {
  local image_dir="$repo_root/firmware/image"
  cat <<EOF
set -e
chroot "\$1" dpkg-divert --quiet --local --rename --divert /usr/sbin/update-initramfs.kinfly \
  --add /usr/sbin/update-initramfs
printf '#!/bin/sh\nexit 0\n' >"\$1/usr/sbin/update-initramfs"
chmod 755 "\$1/usr/sbin/update-initramfs"
install -D -m 644 "$image_dir/initramfs-kinfly.conf" "\$1/etc/initramfs-tools/conf.d/kinfly.conf"
install -D -m 755 "$image_dir/initramfs-kinfly-storage" \
  "\$1/etc/initramfs-tools/hooks/kinfly-storage"
EOF
}

# Shell run by mmdebstrap once every package is in, before the initramfs is made. raspi-firmware's
# hook, which update-initramfs runs, writes the Pi's config.txt and cmdline.txt into /boot/firmware
# from /etc/default/raspi-firmware; it runs again on the drone with every kernel upgrade. What it
# would detect on a Pi it cannot here, so it is told:
#   - the root file system by its UUID (it would take the build machine's root);
#   - the consoles, the serial port last: /dev/console, where systemd and the first boot write,
#     since a drone's board runs headless (the Pi 4's GPIO 14/15 UART is the mini UART, ttyS1);
#   - no cma= (off a Pi 4 it writes cma=64M, which its own note says can stop a Pi 4 booting).
# The hook sources that file, so the file also ends the hook on a board that is not a Pi (every
# board's image has the same root): a UEFI drone's kernel upgrades leave its EFI partition alone.
# While the image is built (KINFLY_IMAGE_BUILD, set for the one update-initramfs run below) no
# board is there to ask. The file is a conffile: dpkg would ask about it only if a raspi-firmware
# upgrade changed it, and Debian 12 keeps 1.20220830+ds-1.
# The mini UART's baud rate follows the VPU's clock, which Debian's note says must stay at 360 MHz
# on a Pi 4 for a readable console: raspi-firmware-custom is appended to config.txt on every run,
# and [pi4] keeps the setting to that family.
raspi_firmware_hook() {
  local root_uuid="$1"
  cat <<EOF
set -e
cat >>"\$1/etc/default/raspi-firmware" <<'SETTINGS'

# kinfly (scripts/build-image.sh): what the hook cannot detect while the image is built, and
# nothing to do on a board that is not a Raspberry Pi.
[ -n "\${KINFLY_IMAGE_BUILD:-}" ] ||
  grep -q 'Raspberry Pi' /sys/firmware/devicetree/base/model 2>/dev/null || exit 0
ROOTPART="UUID=$root_uuid"
CONSOLES="tty0 ttyS1,115200"
CMA=0
SETTINGS
printf '[pi4]\ncore_freq=360\n[all]\n' >"\$1/etc/default/raspi-firmware-custom"
EOF
}

# Files that make the tree a kinfly drone rather than a plain Debian.
customize_root() {
  local root="$1" root_uuid="$2" boot_uuid="$3"
  echo kinfly >"$root/etc/hostname"
  printf '127.0.0.1\tlocalhost\n127.0.1.1\tkinfly\n::1\t\tlocalhost ip6-localhost ip6-loopback\n' \
    >"$root/etc/hosts"
  cat >"$root/etc/fstab" <<EOF
# <file system>	<mount point>	<type>	<options>	<dump>	<pass>
UUID=$root_uuid	/	ext4	defaults,noatime	0	1
UUID=$boot_uuid	/boot/firmware	vfat	defaults,umask=0077,nofail	0	2
EOF
  mkdir -p "$root/boot/firmware"

  # DHCP on every wired and wireless interface; net.ifnames=0 on the kernel command line keeps the
  # Wi-Fi called wlan0, which is what kinfly.conf configures.
  mkdir -p "$root/etc/systemd/network"
  printf '[Match]\nName=eth* wlan*\n\n[Network]\nDHCP=yes\nMulticastDNS=no\n' \
    >"$root/etc/systemd/network/20-kinfly-dhcp.network"
  install -m 644 "$repo_root/firmware/image/10-kinfly-multicast.network" \
    "$root/etc/systemd/network/"
  mkdir -p "$root/etc/systemd/system/wpa_supplicant@.service.d"
  printf '[Unit]\nConditionPathExists=/etc/wpa_supplicant/wpa_supplicant-%%i.conf\n' \
    >"$root/etc/systemd/system/wpa_supplicant@.service.d/kinfly.conf"
  printf '# kinfly-fw environment (kinfly-firstboot rewrites it from kinfly.conf).\n%s\n%s\n' \
    'LCM_DEFAULT_URL=udpm://239.255.76.67:7667?ttl=1' 'KINFLY_MULTICAST_DEV=wlan0' \
    >"$root/etc/default/kinfly-fw"

  # A drone's source is its depth sensor; the package's default (a log replay) suits a laptop.
  sed -i '/^\[source\]/,/^\[/ s/^kind = "log"/kind = "openni"/' "$root/etc/kinfly/kinfly-fw.toml"
  grep -q '^kind = "openni"' "$root/etc/kinfly/kinfly-fw.toml" ||
    die "could not set [source] kind = \"openni\" in /etc/kinfly/kinfly-fw.toml"

  install -D -m 755 "$repo_root/firmware/image/kinfly-firstboot" \
    "$root/usr/libexec/kinfly/kinfly-firstboot"
  install -m 644 "$repo_root/firmware/image/kinfly-firstboot.service" "$root/etc/systemd/system/"
  # Every drone flashed from one image would otherwise share the image's ssh host keys; the first
  # boot makes its own (kinfly-firstboot: ssh-keygen -A).
  rm -f "$root"/etc/ssh/ssh_host_*

  # `systemctl enable` inside the tree (arm64, through qemu) writes the same links as on a board.
  chroot "$root" systemctl enable kinfly-firstboot.service systemd-networkd.service \
    wpa_supplicant@wlan0.service >/dev/null 2>&1
  # The package's own wpa_supplicant.service is NetworkManager's D-Bus one: without D-Bus it only
  # fails; the per-interface instance above is the one that connects.
  chroot "$root" systemctl disable wpa_supplicant.service >/dev/null 2>&1
  [[ -L "$root/etc/systemd/system/multi-user.target.wants/kinfly-fw.service" ]] ||
    die "the kinfly-fw postinst did not enable kinfly-fw.service"
}

# The uefi board's boot files: GRUB as the removable-media EFI loader (what UEFI firmware and
# U-Boot's EFI boot look for) and its menu.
stage_uefi_boot() {
  local root="$1" root_uuid="$2" dir="$3"
  mkdir -p "$dir/EFI/BOOT"
  # grub-mkimage is the build host's, the modules are the image's (same GRUB release): no arm64
  # code runs to make the loader.
  grub-mkimage --format=arm64-efi --directory="$root/usr/lib/grub/arm64-efi" \
    --prefix=/EFI/BOOT --output="$dir/EFI/BOOT/BOOTAA64.EFI" \
    part_msdos fat ext2 normal linux search search_fs_uuid configfile echo gzio efi_gop
  # /vmlinuz and /initrd.img are the kernel package's symlinks to the current kernel, so a kernel
  # upgrade on the drone needs no change here.
  # The last console= is /dev/console, where systemd and the first boot write: the serial port,
  # since a drone's board runs headless; the kernel's own messages go to the screen too.
  cat >"$dir/EFI/BOOT/grub.cfg" <<EOF
set timeout=2
search --no-floppy --fs-uuid --set=root $root_uuid
menuentry "kinfly (Debian 12 arm64)" {
  linux /vmlinuz root=UUID=$root_uuid rw rootwait net.ifnames=0 console=tty1 console=ttyAMA0,115200
  initrd /initrd.img
}
EOF
}

# The rpi4 board's boot files: what raspi-firmware's hook wrote into the tree's /boot/firmware
# (kept aside in $raspi_dir, since that folder is the FAT partition's mount point).
stage_rpi4_boot() {
  local dir="$3" name
  for name in start4.elf fixup4.dat config.txt cmdline.txt bcm2711-rpi-4-b.dtb; do
    [[ -f "$raspi_dir/$name" ]] || die "raspi-firmware's hook left no $name in /boot/firmware"
  done
  cp -a "$raspi_dir"/. "$dir/"
}

# The FAT partition of BOARD's image: its boot files and the provisioning file.
stage_boot_partition() {
  local board="$1" root="$2" root_uuid="$3" dir="$4"
  rm -rf "$dir"
  mkdir -p "$dir"
  "stage_${board}_boot" "$root" "$root_uuid" "$dir"
  install -m 644 "$repo_root/firmware/image/kinfly.conf" \
    "$repo_root/firmware/image/kinfly.conf.example" "$dir/"
}

# The mount points at or below $1, deepest first (findmnt's list output does not escape them).
mounts_below() {
  findmnt -l -n -o TARGET | DIR="$1" awk '$0 == ENVIRON["DIR"] || index($0, ENVIRON["DIR"] "/") == 1' |
    LC_ALL=C sort -r
}

# Unmounts what a killed build left mounted in the tree at $1. A tree mounted by rbind from the
# host shares its propagation, and unmounting in it would unmount the host's own mounts too, so
# every mount is made private first. Anything still mounted stops the build before a removal
# reaches it.
unmount_below() {
  local dir mount_point
  local -a mounts
  dir="$(realpath -m "$1")"
  mapfile -t mounts < <(mounts_below "$dir")
  ((${#mounts[@]})) || return 0
  log "unmounting what a previous build left mounted under $dir"
  # All private before any unmount: an unmount propagates through its parent's peers.
  for mount_point in "${mounts[@]}"; do
    mount --make-private "$mount_point" || die "cannot make $mount_point private"
  done
  for mount_point in "${mounts[@]}"; do
    umount -l "$mount_point" || die "cannot unmount $mount_point (left by a previous build)"
  done
  [[ -z "$(mounts_below "$dir")" ]] || die "still mounted under $dir: $(mounts_below "$dir" | head -1)"
}

# Writes IMAGE: the MBR, the FAT file system from the folder BOOTFS, and the ext4 root file
# system ROOT_EXT4 (of ROOT_MIB MiB).
assemble_image() {
  local out="$1" bootfs="$2" boot_id="$3" root_ext4="$4" root_mib="$5" work="$6"
  local boot_start=2048 sectors_per_mib=2048 disk_id
  local root_start=$((boot_start + boot_mib * sectors_per_mib))
  local total=$((root_start + root_mib * sectors_per_mib))
  disk_id="$(od -An -N4 -tx4 /dev/urandom | tr -d ' ')"
  log "assembling $out"
  rm -f "$work/boot.vfat" "$out.tmp"
  mkfs.vfat -F 32 -n KINFLYBOOT -i "$boot_id" -C "$work/boot.vfat" $((boot_mib * 1024)) >/dev/null
  MTOOLS_SKIP_CHECK=1 mcopy -s -i "$work/boot.vfat" "$bootfs"/* ::/
  truncate -s $((total * 512)) "$out.tmp"
  sfdisk --quiet "$out.tmp" <<EOF
label: dos
label-id: 0x$disk_id
unit: sectors
start=$boot_start, size=$((boot_mib * sectors_per_mib)), type=c, bootable
start=$root_start, size=$((root_mib * sectors_per_mib)), type=83
EOF
  dd if="$work/boot.vfat" of="$out.tmp" bs=1M seek=$((boot_start / sectors_per_mib)) \
    conv=notrunc,sparse status=none
  dd if="$root_ext4" of="$out.tmp" bs=1M seek=$((root_start / sectors_per_mib)) \
    conv=notrunc,sparse status=none
  rm -f "$work/boot.vfat"
  mv "$out.tmp" "$out"
  log "done: $out ($((total / sectors_per_mib)) MiB, $(du -h "$out" | cut -f1) allocated)"
}

main() {
  local deb="" work="" first_image="" board other
  local -A images=()
  while (($#)); do
    case "$1" in
      --deb) deb="$2"; shift 2 ;;
      --image)
        (($# >= 2)) && [[ "$2" == *=?* ]] || die "--image wants BOARD=IMAGE, not '${2:-}'"
        board="${2%%=*}"
        case "$board" in
          uefi | rpi4) ;;
          *) die "unknown board '$board' (boards: uefi rpi4; the Raspberry Pi 5 is not" \
                 "offered, see --help)" ;;
        esac
        [[ -z "${images[$board]:-}" ]] || die "board '$board' given twice"
        images[$board]="$(realpath -m "${2#*=}")"
        for other in "${!images[@]}"; do
          [[ "$other" == "$board" || "${images[$other]}" != "${images[$board]}" ]] ||
            die "boards '$other' and '$board' would both be written to ${images[$board]}"
        done
        first_image="${first_image:-${images[$board]}}"
        shift 2 ;;
      --work) work="$2"; shift 2 ;;
      -h | --help) sed -n '2,29p' "${BASH_SOURCE[0]}"; exit 0 ;;
      *) die "unknown argument '$1'" ;;
    esac
  done
  [[ -f "$deb" && ${#images[@]} -gt 0 ]] ||
    die "usage: build-image.sh --deb DEB --image BOARD=IMAGE [--image BOARD=IMAGE ...] [--work DIR]"
  deb="$(realpath "$deb")"
  work="${work:-$(dirname "$first_image")/image}"
  [[ "$(id -u)" == 0 ]] || die "run as root (mmdebstrap's root mode keeps file owners)"
  ensure_arm64_exec

  local root="$work/root" bootfs="$work/bootfs"
  raspi_dir="$work/raspi-firmware"  # global: stage_rpi4_boot reads it
  local root_uuid boot_id boot_uuid
  root_uuid="$(cat /proc/sys/kernel/random/uuid)"
  boot_id="$(od -An -N4 -tx4 /dev/urandom | tr -d ' ')"
  boot_uuid="$(echo "${boot_id^^}" | sed 's/^\(....\)\(....\)$/\1-\2/')"

  # A build that was killed may have left mmdebstrap's /proc, /sys and /dev mounts in the tree:
  # unmount them, then never let the removal cross into a file system that is still mounted.
  unmount_below "$root"
  rm -rf --one-file-system "$root"
  mkdir -p "$work"
  # file-mirror-automount recreates the .deb's host path inside the tree; a unique folder under
  # /tmp is one that can be removed from the tree afterwards without touching anything else.
  deb_dir="$(mktemp -d /tmp/kinfly-image-deb.XXXXXX)"  # global: the EXIT trap runs after main
  trap 'rm -rf "$deb_dir"' EXIT
  cp "$deb" "$deb_dir/"
  deb="$deb_dir/$(basename "$deb")"
  log "Debian $KINFLY_DEBIAN_SUITE arm64: minbase + ${image_packages[*]} + $(basename "$deb")"
  local packages
  local -a sources
  packages="$(IFS=,; echo "${image_packages[*]}"),$deb"
  mapfile -t sources < <(kinfly_debian_sources main non-free-firmware)
  # Manual pages, translations and most documentation are dropped: nobody reads them on a drone.
  # file-mirror-automount makes the .deb (a host path) visible to dpkg inside the tree.
  # The kernel's postinst and a later trigger would each build the initramfs, minutes apiece under
  # emulation: update-initramfs is diverted to a no-op while packages install and run once at the
  # end, with the initramfs settings of firmware/image/ in place before the kernel arrives.
  mmdebstrap --quiet --variant=minbase --architectures=arm64 \
    --hook-dir=/usr/share/mmdebstrap/hooks/merged-usr \
    --hook-dir=/usr/share/mmdebstrap/hooks/file-mirror-automount \
    --essential-hook="$(essential_hook)" \
    --customize-hook='rm "$1/usr/sbin/update-initramfs"' \
    --customize-hook='chroot "$1" dpkg-divert --quiet --local --rename \
                        --remove /usr/sbin/update-initramfs' \
    --customize-hook="$(raspi_firmware_hook "$root_uuid")" \
    --customize-hook='chroot "$1" env KINFLY_IMAGE_BUILD=1 update-initramfs -c -k all' \
    --dpkgopt='path-exclude=/usr/share/man/*' \
    --dpkgopt='path-exclude=/usr/share/locale/*' \
    --dpkgopt='path-include=/usr/share/locale/locale.alias' \
    --dpkgopt='path-exclude=/usr/share/doc/*' \
    --dpkgopt='path-include=/usr/share/doc/*/copyright' \
    --dpkgopt='path-include=/usr/share/doc/kinfly-fw/*' \
    --include="$packages" \
    "$KINFLY_DEBIAN_SUITE" "$root" "${sources[@]}"

  rm -rf "${root:?}$deb_dir"
  log "configuring the tree"
  customize_root "$root" "$root_uuid" "$boot_uuid"
  # The Pi's boot files go to the rpi4 image's FAT partition; in the root file system their folder
  # is only the mount point.
  rm -rf "$raspi_dir"
  mv "$root/boot/firmware" "$raspi_dir"
  mkdir "$root/boot/firmware"

  log "making the root file system"
  local root_mib
  root_mib=$(( $(du -s --block-size=1M "$root" | cut -f1) * 11 / 10 + root_headroom_mib ))
  rm -f "$work/root.ext4"
  mkfs.ext4 -q -F -L kinfly-root -U "$root_uuid" -d "$root" "$work/root.ext4" "${root_mib}M"
  for board in "${!images[@]}"; do
    stage_boot_partition "$board" "$root" "$root_uuid" "$bootfs"
    assemble_image "${images[$board]}" "$bootfs" "$boot_id" "$work/root.ext4" "$root_mib" "$work"
  done
  rm -f "$work/root.ext4"
}

main "$@"
