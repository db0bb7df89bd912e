"""firmware/image/kinfly-firstboot, the image's first-boot provisioning, run on this machine
against a staging tree (KINFLY_ROOT, KINFLY_BOOT_DIR): kinfly.conf from the FAT partition becomes
the Wi-Fi configuration, the vehicle id in the conffile and the installed key, and both secrets
leave the FAT partition. Values out of range change nothing. wpa_passphrase and chown are stubs on
PATH (the tree's user kinfly does not exist here)."""
from __future__ import annotations

import os
import shutil
import stat
import subprocess
from pathlib import Path

import pytest

from conftest import REPO_ROOT

FIRSTBOOT = REPO_ROOT / "firmware" / "image" / "kinfly-firstboot"
CONFIG = REPO_ROOT / "firmware" / "config" / "kinfly-fw.toml"
MULTICAST_NETWORK = REPO_ROOT / "firmware" / "image" / "10-kinfly-multicast.network"

STUBS = {
    # What wpa_passphrase prints: the passphrase as a comment, then the derived key.
    "wpa_passphrase": '#!/bin/sh\nprintf \'network={\\n\\tssid="%s"\\n\\t#psk="%s"\\n'
                      '\\tpsk=0123abcd\\n}\\n\' "$1" "$2"\n',
    "chown": '#!/bin/sh\necho "$@" >>"$STUB_LOG"\n',
}


@pytest.fixture
def tree(tmp_path: Path) -> dict[str, Path]:
    root, boot, stubs = tmp_path / "root", tmp_path / "boot", tmp_path / "stubs"
    network = root / "etc" / "systemd" / "network"
    for folder in (root / "etc" / "kinfly", root / "etc" / "default", network, boot, stubs):
        folder.mkdir(parents=True)
    shutil.copy(CONFIG, root / "etc" / "kinfly" / "kinfly-fw.toml")
    shutil.copy(MULTICAST_NETWORK, network)
    (root / "etc" / "hosts").write_text("127.0.0.1\tlocalhost\n127.0.1.1\tkinfly\n")
    (root / "etc" / "hostname").write_text("kinfly\n")
    for name, body in STUBS.items():
        (stubs / name).write_text(body)
        (stubs / name).chmod(0o755)
    return {"root": root, "boot": boot, "stubs": stubs, "log": tmp_path / "stub.log"}


def firstboot(tree: dict[str, Path]) -> subprocess.CompletedProcess:
    env = {**os.environ, "KINFLY_ROOT": str(tree["root"]), "KINFLY_BOOT_DIR": str(tree["boot"]),
           "PATH": f"{tree['stubs']}:{os.environ['PATH']}", "STUB_LOG": str(tree["log"])}
    run = subprocess.run(["sh", str(FIRSTBOOT)], capture_output=True, text=True, env=env,
                         timeout=30)
    assert run.returncode == 0, run.stdout + run.stderr
    return run


def test_provisioning_file_configures_the_drone_and_leaves(tree: dict[str, Path]) -> None:
    root, boot = tree["root"], tree["boot"]
    (boot / "kinfly.conf").write_text(
        "# a comment\r\nwifi_ssid = field net\r\nwifi_passphrase=correct horse\r\n"
        "wifi_country=DE\r\nvehicle_id=42\r\nhostname=drone42\r\n"
        "ssh_authorized_key=ssh-ed25519 AAAAC3Nz me@laptop\r\nmulticast_dev=wlan1\r\n")
    (boot / "vehicle.key").write_bytes(bytes(range(32)))
    run = firstboot(tree)
    assert "applied and removed" in run.stdout
    assert not (boot / "kinfly.conf").exists() and not (boot / "vehicle.key").exists()

    wpa = root / "etc" / "wpa_supplicant" / "wpa_supplicant-wlan0.conf"
    assert stat.S_IMODE(wpa.stat().st_mode) == 0o600
    text = wpa.read_text()
    assert "country=DE" in text and 'ssid="field net"' in text and "psk=0123abcd" in text
    assert "correct horse" not in text  # only the derived key is stored

    config = (root / "etc" / "kinfly" / "kinfly-fw.toml").read_text()
    assert "\nid = 42  # 0..65535" in config
    # Nothing but the id line changed.
    original = CONFIG.read_text().splitlines()
    changed = [a for a, b in zip(original, config.splitlines()) if a != b]
    assert len(changed) == 1 and changed[0].startswith("id = ")

    key = root / "etc" / "kinfly" / "vehicle.key"
    assert key.read_bytes() == bytes(range(32))
    assert stat.S_IMODE(key.stat().st_mode) == 0o600
    assert tree["log"].read_text().split() == ["kinfly:kinfly", str(key)]

    assert (root / "etc" / "hostname").read_text() == "drone42\n"
    assert "127.0.1.1\tdrone42" in (root / "etc" / "hosts").read_text()
    assert (root / "root" / ".ssh" / "authorized_keys").read_text() == \
        "ssh-ed25519 AAAAC3Nz me@laptop\n"
    assert "KINFLY_MULTICAST_DEV=wlan1" in (root / "etc" / "default" / "kinfly-fw").read_text()
    # The route to the multicast group comes and goes with that interface (systemd-networkd).
    network = (root / "etc" / "systemd" / "network" / MULTICAST_NETWORK.name).read_text()
    assert "\nName=wlan1\n" in network and "\nDestination=239.0.0.0/8\n" in network


def test_a_ground_peer_turns_on_unicast(tree: dict[str, Path]) -> None:
    root, boot = tree["root"], tree["boot"]
    (boot / "kinfly.conf").write_text("ground_peer=192.168.4.10:7668\n")
    assert "unicast to the ground station at 192.168.4.10:7668" in firstboot(tree).stdout
    config = (root / "etc" / "kinfly" / "kinfly-fw.toml").read_text()
    changed = [b for a, b in zip(CONFIG.read_text().splitlines(), config.splitlines()) if a != b]
    assert len(changed) == 1 and changed[0].startswith('peers = "192.168.4.10:7668"  # ')
    # Nothing multicast leaves the drone: the peers carry it all.
    assert "LCM_DEFAULT_URL=memq://" in (root / "etc" / "default" / "kinfly-fw").read_text()
    # Provisioned again without it: multicast again.
    (boot / "kinfly.conf").write_text("vehicle_id=3\n")
    firstboot(tree)
    config = (root / "etc" / "kinfly" / "kinfly-fw.toml").read_text()
    assert '\npeers = ""  # ' in config
    assert "LCM_DEFAULT_URL=udpm://" in (root / "etc" / "default" / "kinfly-fw").read_text()


def test_bad_values_change_nothing(tree: dict[str, Path]) -> None:
    root, boot = tree["root"], tree["boot"]
    (boot / "kinfly.conf").write_text("wifi_ssid=net\nwifi_passphrase=short\nvehicle_id=70000\n"
                                      "hostname=bad;name\nground_peer=ground;reboot\n")
    run = firstboot(tree)
    assert "8..63 characters" in run.stdout
    assert "out of range" in run.stdout
    assert "hostname 'bad;name'" in run.stdout
    assert "ground_peer 'ground;reboot' is not ADDRESS:PORT" in run.stdout
    assert not (root / "etc" / "wpa_supplicant").exists()
    assert (root / "etc" / "kinfly" / "kinfly-fw.toml").read_text() == CONFIG.read_text()
    assert (root / "etc" / "hostname").read_text() == "kinfly\n"


def test_without_a_provisioning_file_nothing_happens(tree: dict[str, Path]) -> None:
    assert "nothing to configure" in firstboot(tree).stdout
    config = tree["root"] / "etc" / "kinfly" / "kinfly-fw.toml"
    assert config.read_text() == CONFIG.read_text()
