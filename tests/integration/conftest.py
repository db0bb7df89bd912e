"""Fixtures shared by the integration tests: where the repository, the built binaries and the
shared real data are.

The shared data (`<repo>/../shared/data`, or $KINFLY_DATA) is not part of the repository. Without
it the tests that need it are skipped on a developer's machine, but fail under CI (CI=true), where
a skip would hide that the accuracy checks never ran."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "tests" / "tools"))

import kinfly_eval  # noqa: E402  (needs the sys.path entry above)


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
