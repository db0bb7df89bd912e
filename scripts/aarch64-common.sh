# Sourced by the aarch64 scripts: which Debian release and mirrors the sysroot and the image come
# from, so the firmware is built against exactly what the board runs.
# shellcheck shell=bash
KINFLY_DEBIAN_SUITE="${KINFLY_DEBIAN_SUITE:-bookworm}"
: "${KINFLY_DEBIAN_MIRROR:=http://deb.debian.org/debian}"
: "${KINFLY_DEBIAN_SECURITY_MIRROR:=http://deb.debian.org/debian-security}"
KINFLY_DEBIAN_MIRRORS=(
  "deb $KINFLY_DEBIAN_MIRROR $KINFLY_DEBIAN_SUITE main"
  "deb $KINFLY_DEBIAN_MIRROR $KINFLY_DEBIAN_SUITE-updates main"
  "deb $KINFLY_DEBIAN_SECURITY_MIRROR $KINFLY_DEBIAN_SUITE-security main"
)
