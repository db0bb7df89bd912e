"""Fixtures shared by the Python tests: where the repository, the built binaries and the
shared real data are.

The shared data (`<repo>/../shared/data`, or $KINFLY_DATA) is not part of the repository. Without
it the tests that need it are skipped on a developer's machine, but fail under CI (CI=true), where
a skip would hide that the accuracy checks never ran."""
from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT / "tests" / "tools"))
sys.path.insert(0, str(REPO_ROOT / "tests" / "eval"))
sys.path.insert(0, str(REPO_ROOT / "scripts"))  # netns.py, shared with make demo

import kinfly_eval  # noqa: E402  (needs the sys.path entry above)
from netns import LinkShape, NetnsUnavailable, network_namespace  # noqa: E402


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "aarch64: needs the cross build and the image (make test-aarch64); "
                   "`make python-test` leaves these out")


def require_built(path: Path, make_target: str) -> Path:
    """PATH, made by MAKE_TARGET. Missing: skipped on a developer's machine, a failure under CI,
    where a skip would hide that the checks never ran."""
    if path.exists():
        return path
    message = f"{path} is not built: run `make {make_target}` first"
    if os.environ.get("CI"):
        pytest.fail(message + "; CI must run the aarch64 checks", pytrace=False)
    pytest.skip(message)


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


def _built_binary(name: str, env_var: str) -> Path:
    """build/bin/NAME, or $ENV_VAR. A missing binary is a failure, not a skip: the tests that ask
    for it exist to exercise it."""
    path = Path(os.environ.get(env_var, REPO_ROOT / "build" / "bin" / name))
    if not os.access(path, os.X_OK):
        pytest.fail(f"{path} is not built: run `make build` first (or set {env_var})",
                    pytrace=False)
    return path


def built(relative: str) -> Path:
    """A binary of the Release build (build/...). Missing is a failure, not a skip."""
    path = REPO_ROOT / "build" / relative
    if not os.access(path, os.X_OK):
        pytest.fail(f"{path} is not built: run `make build` first", pytrace=False)
    return path


@pytest.fixture(scope="session")
def fuse_bin() -> Path:
    return _built_binary("kinfly-fuse", "KINFLY_FUSE")


@pytest.fixture(scope="session")
def codec_bench_bin() -> Path:
    return _built_binary("kinfly-codec-bench", "KINFLY_CODEC_BENCH")


def wait_for_line(process: subprocess.Popen, text: str) -> None:
    """Reads the process's stderr until a line contains text (a readiness message)."""
    assert process.stderr is not None
    for line in process.stderr:
        if text in line:
            return
    pytest.fail(f"process exited before printing {text!r}")


@pytest.fixture(scope="session")
def sample_dir() -> Path:
    """The 60-frame TUM teddy sample committed in tests/data."""
    return REPO_ROOT / "tests" / "data" / "tum_teddy_sample"


def _require_shared(path: Path) -> Path:
    if path.exists():
        return path
    message = (f"shared data not found: {path} (expected <repo>/../shared/data, or set "
               f"KINFLY_DATA)")
    if os.environ.get("CI"):
        pytest.fail(message + "; CI must run the real-data checks", pytrace=False)
    pytest.skip(message)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    return _require_shared(kinfly_eval.data_root(REPO_ROOT))


@pytest.fixture(scope="session")
def tum_sequence(shared_data: Path) -> Path:
    """The 200-frame TUM freiburg3_teddy sequence with its ground truth."""
    return _require_shared(shared_data / kinfly_eval.TUM_SEQUENCE_SUBDIR)


@pytest.fixture(scope="session")
def replica_dir(shared_data: Path) -> Path:
    """The Replica office0 sample (4 frames, trajectory, GT mesh)."""
    return _require_shared(shared_data / kinfly_eval.REPLICA_SUBDIR)


def _no_netns(err: NetnsUnavailable) -> None:
    if os.environ.get("CI"):
        pytest.fail(f"CI must run the multi-process LCM tests: {err}", pytrace=False)
    pytest.skip(str(err))


@pytest.fixture
def netns() -> Iterator[list[str]]:
    """A private network namespace (scripts/netns.py) for LCM between processes; yields the
    command prefix that runs a program in it. Unavailable: a skip here, a failure under CI."""
    try:
        with network_namespace("test") as prefix:
            yield prefix
    except NetnsUnavailable as err:
        _no_netns(err)


@pytest.fixture
def wifi_netns() -> Iterator[Callable[[LinkShape], list[str]]]:
    """Makes private network namespaces whose `lo` is shaped like a Wi-Fi link:
    `prefix = wifi_netns(LinkShape(loss=0.05, loss_run_packets=5))` (scripts/netns.py), as many
    as the test asks for, all removed after it. Unavailable: a skip here, a failure under CI."""
    with contextlib.ExitStack() as namespaces:
        def make(shape: LinkShape) -> list[str]:
            try:
                return namespaces.enter_context(network_namespace("wifi", shape))
            except NetnsUnavailable as err:
                _no_netns(err)
                raise  # not reached: skip and fail raise

        yield make


@pytest.fixture(scope="session")
def sample_log(sample_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The committed TUM sample as an LCM flight log (kinfly-tum-to-log, vehicle 1)."""
    out = tmp_path_factory.mktemp("log") / "sample.lcmlog"
    subprocess.run([built("bin/kinfly-tum-to-log"), "--tum", sample_dir, "--out", out],
                   check=True, capture_output=True)
    return out
