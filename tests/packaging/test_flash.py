"""scripts/flash.sh refuses every target that is not a removable, unused whole disk, and any run
without --yes. Nothing here writes to a disk: the block devices are loop devices over files in
tmp_path, and every call that could pass the checks has --dry-run.

Loop devices and mounts need root; without them those tests are skipped on a developer's machine
and fail under CI."""
from __future__ import annotations

import os
import shutil
import stat
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from conftest import REPO_ROOT

FLASH = REPO_ROOT / "scripts" / "flash.sh"
MIB = 1 << 20


def flash(*args: object, sysfs: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    if sysfs is not None:
        env["KINFLY_SYSFS"] = str(sysfs)
    return subprocess.run([str(FLASH), *map(str, args)], capture_output=True, text=True,
                          timeout=30, env=env)


def refused(result: subprocess.CompletedProcess, reason: str) -> bool:
    return result.returncode != 0 and "refused" in result.stderr and reason in result.stderr


@pytest.fixture
def image(tmp_path: Path) -> Path:
    path = tmp_path / "kinfly.img"
    path.write_bytes(b"\0" * MIB)
    return path


def _needs_root(message: str) -> None:
    if os.environ.get("CI"):
        pytest.fail(f"CI must run the flash refusal tests: {message}", pytrace=False)
    pytest.skip(message)


def _losetup(*args: str) -> str:
    if os.geteuid() != 0 or not shutil.which("losetup"):
        _needs_root("loop devices need root and losetup")
    run = subprocess.run(["losetup", *args], capture_output=True, text=True)
    if run.returncode != 0:
        _needs_root(f"losetup {' '.join(args)}: {run.stderr.strip()}")
    return run.stdout.strip()


@pytest.fixture
def loop_device(tmp_path: Path) -> Iterator[str]:
    """A 16 MiB loop device with one partition (loopNp1), backed by a file."""
    backing = tmp_path / "disk.img"
    with backing.open("wb") as f:
        f.truncate(16 * MIB)
    subprocess.run(["sfdisk", "--quiet", backing], input="start=2048, type=83\n", text=True,
                   check=True, capture_output=True)
    device = _losetup("--find", "--show", "--partscan", str(backing))
    try:
        yield device
    finally:
        subprocess.run(["losetup", "--detach", device], check=False)


def fake_removable_sysfs(tmp_path: Path, device: str) -> Path:
    """A copy of DEVICE's sysfs entries with removable = 1, as an SD card reader reports."""
    name = os.path.basename(device)
    real = Path("/sys/class/block") / name
    fake = tmp_path / "sys" / "class" / "block" / name
    (fake / "holders").mkdir(parents=True)
    for entry in ("dev", "size"):
        (fake / entry).write_text((real / entry).read_text())
    (fake / "removable").write_text("1\n")
    return tmp_path / "sys"


def test_refuses_a_regular_file(image: Path, tmp_path: Path) -> None:
    target = tmp_path / "not-a-disk"
    target.write_bytes(b"keep me")
    assert refused(flash("--image", image, "--device", target, "--yes"), "not a block device")
    assert target.read_bytes() == b"keep me"


def test_refuses_a_missing_device_and_a_missing_image(image: Path, tmp_path: Path) -> None:
    assert refused(flash("--image", image, "--device", tmp_path / "sdz", "--yes"),
                   "does not exist")
    assert refused(flash("--image", tmp_path / "none.img", "--device", "/dev/null", "--yes"),
                   "is not a file")


def test_refuses_a_non_removable_disk(image: Path, loop_device: str) -> None:
    # Loop devices, like internal disks, report removable = 0.
    result = flash("--image", image, "--device", loop_device, "--yes", "--dry-run")
    assert refused(result, "not a removable disk"), result.stderr


def test_refuses_a_partition(image: Path, loop_device: str, tmp_path: Path) -> None:
    partition = loop_device + "p1"
    sys_entry = Path("/sys/class/block") / os.path.basename(partition)
    if not sys_entry.exists():
        subprocess.run(["partx", "--add", loop_device], check=True, capture_output=True)
    if not os.path.exists(partition):
        # Without udev (a container) the kernel knows the partition but nobody made its node.
        major, minor = (Path("/sys/class/block") / os.path.basename(partition) / "dev"
                        ).read_text().split(":")
        partition = str(tmp_path / os.path.basename(partition))
        os.mknod(partition, 0o600 | stat.S_IFBLK, os.makedev(int(major), int(minor)))
    result = flash("--image", image, "--device", partition, "--yes", "--dry-run")
    assert refused(result, "is a partition"), result.stderr


def test_refuses_a_disk_with_a_mounted_file_system(image: Path, loop_device: str,
                                                   tmp_path: Path) -> None:
    subprocess.run(["mkfs.ext4", "-q", "-F", loop_device], check=True, capture_output=True)
    mount_point = tmp_path / "mnt"
    mount_point.mkdir()
    mounted = subprocess.run(["mount", loop_device, mount_point], capture_output=True, text=True)
    if mounted.returncode != 0:
        _needs_root(f"mount: {mounted.stderr.strip()}")
    try:
        # Even where it would count as removable, a mounted disk is refused.
        sysfs = fake_removable_sysfs(tmp_path, loop_device)
        result = flash("--image", image, "--device", loop_device, "--yes", "--dry-run",
                       sysfs=sysfs)
        assert refused(result, "is mounted"), result.stderr
    finally:
        subprocess.run(["umount", mount_point], check=True)


def test_removable_disk_needs_the_confirmation_and_room(image: Path, loop_device: str,
                                                        tmp_path: Path) -> None:
    sysfs = fake_removable_sysfs(tmp_path, loop_device)
    result = flash("--image", image, "--device", loop_device, "--dry-run", sysfs=sysfs)
    assert refused(result, "--yes"), result.stderr
    big = tmp_path / "big.img"
    with big.open("wb") as f:
        f.truncate(64 * MIB)
    result = flash("--image", big, "--device", loop_device, "--yes", "--dry-run", sysfs=sysfs)
    assert refused(result, "the image needs 64 MiB"), result.stderr
    result = flash("--image", image, "--device", loop_device, "--yes", "--dry-run", sysfs=sysfs)
    assert result.returncode == 0, result.stderr
    assert f"would run: dd if={image} of={loop_device}" in result.stdout
