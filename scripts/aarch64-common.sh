# Sourced by the aarch64 scripts: which Debian release and mirrors the sysroot and the image come
# from, so the firmware is built against exactly what the board runs.
# shellcheck shell=bash
KINFLY_DEBIAN_SUITE="${KINFLY_DEBIAN_SUITE:-bookworm}"
: "${KINFLY_DEBIAN_MIRROR:=http://deb.debian.org/debian}"
: "${KINFLY_DEBIAN_SECURITY_MIRROR:=http://deb.debian.org/debian-security}"
# The sources.list lines of the release, its updates and its security fixes for the components
# given: the sysroot needs main only; the image also non-free-firmware, where Debian keeps the
# Raspberry Pi's boot firmware and its Wi-Fi chip's firmware.
kinfly_debian_sources() {
  printf '%s\n' "deb $KINFLY_DEBIAN_MIRROR $KINFLY_DEBIAN_SUITE $*" \
    "deb $KINFLY_DEBIAN_MIRROR $KINFLY_DEBIAN_SUITE-updates $*" \
    "deb $KINFLY_DEBIAN_SECURITY_MIRROR $KINFLY_DEBIAN_SUITE-security $*"
}
