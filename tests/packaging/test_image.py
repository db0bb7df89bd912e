"""The kinfly-fw .deb (make package-aarch64) and the flashable image (make image), read without
mounting anything: the partition table, both file systems, the files that make it a kinfly drone,
and kinfly-fw --version run from the image's own root tree under qemu-aarch64.

Missing package or image: skipped on a developer's machine, a failure under CI."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from conftest import REPO_ROOT, require_built

pytestmark = pytest.mark.aarch64

AARCH64_DIR = Path(os.environ.get("KINFLY_AARCH64_DIR", REPO_ROOT / "build-aarch64"))
SECTOR = 512


def run(*command: object) -> str:
    return subprocess.run(list(map(str, command)), check=True, capture_output=True, text=True,
                          timeout=300).stdout


@pytest.fixture(scope="module")
def deb() -> Path:
    found = sorted((AARCH64_DIR / "pkg").glob("kinfly-fw_*_arm64.deb"))
    return require_built(found[-1] if found else AARCH64_DIR / "pkg" / "kinfly-fw_arm64.deb",
                         "package-aarch64")


@pytest.fixture(scope="module")
def image() -> Path:
    return require_built(Path(os.environ.get("KINFLY_IMAGE", AARCH64_DIR / "kinfly-arm64.img")),
                         "image")


@pytest.fixture(scope="module")
def partitions(image: Path) -> list[dict]:
    table = json.loads(run("sfdisk", "--json", image))["partitiontable"]
    assert table["label"] == "dos"
    return table["partitions"]


def extract(image: Path, partition: dict, out: Path) -> Path:
    """One partition copied out of the image (sparse), for debugfs, mtools and e2fsck."""
    run("dd", f"if={image}", f"of={out}", f"bs={SECTOR}", f"skip={partition['start']}",
        f"count={partition['size']}", "conv=sparse", "status=none")
    return out


@pytest.fixture(scope="module")
def boot_fs(image: Path, partitions: list[dict], tmp_path_factory: pytest.TempPathFactory) -> Path:
    return extract(image, partitions[0], tmp_path_factory.mktemp("image") / "boot.vfat")


@pytest.fixture(scope="module")
def root_fs(image: Path, partitions: list[dict], tmp_path_factory: pytest.TempPathFactory) -> Path:
    return extract(image, partitions[1], tmp_path_factory.mktemp("image") / "root.ext4")


def debugfs(fs: Path, request: str) -> str:
    return run("debugfs", "-R", request, fs)


def fs_uuid(fs: Path) -> str:
    return run("blkid", "-p", "-s", "UUID", "-o", "value", fs).strip()


def test_package_holds_the_firmware_config_and_unit(deb: Path) -> None:
    fields = {name: run("dpkg-deb", "--field", deb, name).strip()
              for name in ("Package", "Architecture", "Depends")}
    assert fields["Package"] == "kinfly-fw"
    assert fields["Architecture"] == "arm64"
    # Computed from the binaries' DT_NEEDED, so the engine's libraries and the link's must be there.
    for runtime in ("libc6", "libstdc++6", "libgomp1", "liblcm1", "libsodium23", "libzstd1",
                    "libcm256cc1"):
        assert re.search(rf"(^|, ){re.escape(runtime)}( |,|$)", fields["Depends"]), fields
    files = run("dpkg-deb", "--contents", deb)
    for path in ("./usr/bin/kinfly-fw", "./usr/bin/kinfly-keygen", "./etc/kinfly/kinfly-fw.toml",
                 "./lib/systemd/system/kinfly-fw.service", "./usr/lib/sysusers.d/kinfly-fw.conf"):
        assert re.search(rf" {re.escape(path)}$", files, re.M), path
    control = Path(run("mktemp", "-d").strip())
    try:
        run("dpkg-deb", "--control", deb, control)
        assert (control / "conffiles").read_text().split() == ["/etc/kinfly/kinfly-fw.toml"]
        assert os.access(control / "postinst", os.X_OK)
    finally:
        shutil.rmtree(control)


def test_partition_table_has_boot_and_root(partitions: list[dict]) -> None:
    assert [p["type"] for p in partitions] == ["c", "83"]  # FAT32 (LBA), Linux
    assert partitions[0].get("bootable") is True
    assert partitions[0]["start"] % 2048 == 0 and partitions[1]["start"] % 2048 == 0  # 1 MiB


def test_file_systems_are_clean_and_referenced_by_uuid(boot_fs: Path, root_fs: Path) -> None:
    assert run("blkid", "-p", "-s", "TYPE", "-o", "value", boot_fs).strip() == "vfat"
    assert run("blkid", "-p", "-s", "TYPE", "-o", "value", root_fs).strip() == "ext4"
    subprocess.run(["e2fsck", "-fn", root_fs], check=True, capture_output=True, timeout=300)
    subprocess.run(["fsck.vfat", "-n", boot_fs], check=True, capture_output=True, timeout=60)
    fstab = debugfs(root_fs, "cat /etc/fstab")
    assert f"UUID={fs_uuid(root_fs)}\t/\t" in fstab
    assert f"UUID={fs_uuid(boot_fs)}\t/boot/firmware\t" in fstab
    grub_cfg = run("mtype", "-i", boot_fs, "::/EFI/BOOT/grub.cfg")
    assert f"--set=root {fs_uuid(root_fs)}" in grub_cfg
    assert f"root=UUID={fs_uuid(root_fs)}" in grub_cfg
    # The serial port is /dev/console (the last console=): systemd's and the first boot's
    # messages reach a headless board's serial line.
    assert re.findall(r"console=(\S+)", grub_cfg)[-1] == "ttyAMA0,115200", grub_cfg


def test_boot_partition_has_the_loader_and_provisioning_file(boot_fs: Path) -> None:
    env = {**os.environ, "MTOOLS_SKIP_CHECK": "1"}
    listing = subprocess.run(["mdir", "-b", "-/", "-i", boot_fs, "::/"], check=True,
                             capture_output=True, text=True, env=env).stdout
    for name in ("::/EFI/BOOT/BOOTAA64.EFI", "::/EFI/BOOT/grub.cfg", "::/kinfly.conf",
                 "::/kinfly.conf.example"):
        assert name in listing.splitlines(), listing
    assert "wifi_ssid" in run("mtype", "-i", boot_fs, "::/kinfly.conf")


def stat(root_fs: Path, path: str) -> str:
    out = debugfs(root_fs, f'stat "{path}"')
    assert "Inode:" in out, f"{path} not in the image"
    return out


def test_root_has_firmware_config_units_and_first_boot(root_fs: Path) -> None:
    for path in ("/usr/bin/kinfly-fw", "/usr/bin/kinfly-keygen", "/etc/kinfly/kinfly-fw.toml",
                 "/usr/lib/systemd/system/kinfly-fw.service",
                 "/usr/libexec/kinfly/kinfly-firstboot",
                 "/etc/systemd/system/kinfly-firstboot.service", "/etc/default/kinfly-fw",
                 "/etc/systemd/network/10-kinfly-multicast.network", "/vmlinuz", "/initrd.img",
                 # The Wi-Fi's regulatory database (wireless-regdb; its postinst links it), or
                 # the kernel says "failed to load regulatory.db" and wifi_country does nothing.
                 "/usr/lib/firmware/regulatory.db-debian", "/usr/lib/firmware/regulatory.db"):
        stat(root_fs, path)
    assert "Mode:  0755" in stat(root_fs, "/usr/libexec/kinfly/kinfly-firstboot")
    # The multicast route comes and goes with the Wi-Fi (systemd-networkd), so kinfly-fw, which
    # waits for it, links whenever the Wi-Fi is up.
    network = debugfs(root_fs, 'cat "/etc/systemd/network/10-kinfly-multicast.network"')
    assert "Name=wlan0" in network and "Destination=239.0.0.0/8" in network, network
    wants = "/etc/systemd/system/multi-user.target.wants"
    for unit, target in (("kinfly-fw.service", "/lib/systemd/system/kinfly-fw.service"),
                         ("kinfly-firstboot.service",
                          "/etc/systemd/system/kinfly-firstboot.service")):
        link = stat(root_fs, f"{wants}/{unit}")
        assert "Type: symlink" in link and target in link, link
    # Without D-Bus the package's wpa_supplicant.service can only fail (a degraded boot).
    assert "Inode:" not in debugfs(root_fs, f'stat "{wants}/wpa_supplicant.service"')
    unit = debugfs(root_fs, "cat /usr/lib/systemd/system/kinfly-fw.service")
    assert "ExecStart=/usr/bin/kinfly-fw --config /etc/kinfly/kinfly-fw.toml\n" in unit
    assert "Restart=on-failure" in unit and "User=kinfly" in unit
    config = debugfs(root_fs, "cat /etc/kinfly/kinfly-fw.toml")
    assert re.search(r'^\[source\]\nkind = "openni"', config, re.M), "the drone reads its sensor"
    # The postinst ran inside the image: the service user exists.
    assert re.search(r"^kinfly:", debugfs(root_fs, "cat /etc/passwd"), re.M)
    # No ssh host keys shared by every drone flashed from this image.
    assert "ssh_host_" not in debugfs(root_fs, "ls -l /etc/ssh")


def copy_symlink(root_fs: Path, path: str, root: Path) -> None:
    target = re.search(r'Fast link dest: "([^"]+)"', stat(root_fs, path))
    assert target, f"{path} is not a symlink in the image"
    (root / path.lstrip("/")).symlink_to(target.group(1))


def test_firmware_runs_from_the_image_root_under_qemu(root_fs: Path, tmp_path: Path) -> None:
    """kinfly-fw with the image's own loader and libraries, not the build sysroot's: the binary
    and /usr/lib/aarch64-linux-gnu read out of the ext4 file system, the loader's links as the
    image has them (merged /usr: /lib -> usr/lib)."""
    root = tmp_path / "root"
    for folder in ("usr/bin", "usr/lib"):
        (root / folder).mkdir(parents=True)
    debugfs(root_fs, f'dump -p /usr/bin/kinfly-fw "{root}/usr/bin/kinfly-fw"')
    debugfs(root_fs, f'rdump /usr/lib/aarch64-linux-gnu "{root}/usr/lib"')
    copy_symlink(root_fs, "/lib", root)
    copy_symlink(root_fs, "/usr/lib/ld-linux-aarch64.so.1", root)
    run_ = subprocess.run([shutil.which("qemu-aarch64") or "qemu-aarch64", "-L", root,
                           root / "usr/bin/kinfly-fw", "--version"],
                          capture_output=True, text=True, timeout=60)
    assert run_.returncode == 0, run_.stderr
    assert run_.stdout.startswith("kinfly-fw "), run_.stdout
