"""scripts/deploy.sh against a pretend drone: ssh and scp are stubs that run the remote side on
this machine, with dpkg, systemctl and sudo stubs that log what they are asked to do. Checks the
order of the install, the architecture check and that the copy is removed either way."""
from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from conftest import REPO_ROOT

DEPLOY = REPO_ROOT / "scripts" / "deploy.sh"

STUBS = {
    # scp [opts] FILE HOST:PATH -> cp FILE PATH; ssh [opts] HOST COMMAND... -> COMMAND here.
    "scp": '#!/bin/sh\nfor a; do last="$a"; done\nfor a; do case "$a" in -*|"$last") ;; '
           '*) src="$a" ;; esac; done\ncp "$src" "${last#*:}"\n',
    "ssh": '#!/bin/sh\nwhile [ "${1#-}" != "$1" ]; do case "$1" in -o) shift 2 ;; *) shift ;; '
           'esac; done\nshift\nexec "$@"\n',
    "dpkg": '#!/bin/sh\nif [ "$1" = --print-architecture ]; then echo "$DRONE_ARCH"; exit; fi\n'
            'echo "dpkg $*" >>"$STUB_LOG"\n',
    "systemctl": '#!/bin/sh\necho "systemctl $*" >>"$STUB_LOG"\n',
    "sudo": '#!/bin/sh\n[ "$1" = -n ] && shift\necho "sudo" >>"$STUB_LOG"\nexec "$@"\n',
}


@pytest.fixture
def drone(tmp_path: Path) -> dict:
    stubs = tmp_path / "stubs"
    stubs.mkdir()
    for name, body in STUBS.items():
        (stubs / name).write_text(body)
        (stubs / name).chmod(0o755)
    deb = tmp_path / "kinfly-fw_0.1.0_arm64.deb"
    package = tmp_path / "pkg"
    (package / "DEBIAN").mkdir(parents=True)
    (package / "DEBIAN" / "control").write_text(
        "Package: kinfly-fw\nVersion: 0.1.0\nArchitecture: arm64\nMaintainer: t <t@t>\n"
        "Description: test\n")
    subprocess.run(["dpkg-deb", "--build", "--root-owner-group", package, deb], check=True,
                   capture_output=True)
    return {"stubs": stubs, "deb": deb, "log": tmp_path / "stub.log"}


def deploy(drone: dict, arch: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PATH": f"{drone['stubs']}:{os.environ['PATH']}",
           "STUB_LOG": str(drone["log"]), "DRONE_ARCH": arch}
    return subprocess.run([str(DEPLOY), "--host", "pilot@drone7", "--deb", str(drone["deb"])],
                          capture_output=True, text=True, env=env, timeout=30)


def test_installs_keeping_the_configuration_and_restarts(drone: dict) -> None:
    run = deploy(drone, "arm64")
    assert run.returncode == 0, run.stdout + run.stderr
    calls = drone["log"].read_text().splitlines()
    copied = f"/tmp/{drone['deb'].name}"
    install = f"dpkg --install --force-confold {copied}"
    assert install in calls and "systemctl restart kinfly-fw.service" in calls, calls
    assert calls.index(install) < calls.index("systemctl restart kinfly-fw.service")
    if os.geteuid() != 0:
        assert "sudo" in calls
    assert not Path(copied).exists()


def test_refuses_a_drone_of_another_architecture(drone: dict) -> None:
    run = deploy(drone, "armhf")
    assert run.returncode != 0
    assert "the drone is armhf, the package is arm64" in run.stderr
    assert not drone["log"].exists()  # neither dpkg nor systemctl was called
    assert not Path(f"/tmp/{drone['deb'].name}").exists()


def test_needs_a_host(tmp_path: Path) -> None:
    run = subprocess.run([str(DEPLOY)], capture_output=True, text=True, timeout=30)
    assert run.returncode != 0 and "--host USER@DRONE" in run.stderr
