"""The loop checks' thread and process (loops.py): closing the station abandons a check under way
and ends its process, so a Ctrl-C never waits for a registration to finish."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import psutil

from kinfly_ground.loops import LoopCloser
from kinfly_ground.registration import LoopCheck
from kinfly_ground.submaps import LoopCandidate

# Far longer than the test: a process still alive after close() is still checking.
SLOW_CHECK_S = 120.0
# Bounds, not waits: a spawned process starts in a second or two, on a busy machine in several.
CHECK_STARTED_TIMEOUT_S = 60.0
PROCESS_GONE_TIMEOUT_S = 10.0
POLL_S = 0.05


def slow_check(started: str, seconds: float) -> LoopCheck:
    """Stands in for a registration (module level: the check process imports it by name)."""
    Path(started).touch()
    time.sleep(seconds)
    raise AssertionError("close() did not end the check")


class _Chain:
    def __init__(self, started: Path) -> None:
        self._started = started

    def check_arguments(self, candidate: LoopCandidate) -> tuple[str, float]:
        return str(self._started), SLOW_CHECK_S


def test_close_abandons_a_running_check_and_ends_its_process(tmp_path: Path) -> None:
    started = tmp_path / "check started"
    chain = _Chain(started)
    closer = LoopCloser(log=print, check=slow_check)
    before = {child.pid for child in psutil.Process().children()}
    try:
        closer.submit(chain, [LoopCandidate(older=0, newer=2, T_older_newer_guess=np.eye(4))])
        deadline = time.monotonic() + CHECK_STARTED_TIMEOUT_S
        while not started.exists():
            assert time.monotonic() < deadline, "the check never started"
            time.sleep(POLL_S)  # polling for a file the other process makes
        # Spawning may also start multiprocessing's resource tracker, which is not the check's.
        workers = [child for child in psutil.Process().children()
                   if child.pid not in before and "spawn_main" in " ".join(child.cmdline())]
        assert len(workers) == 1, psutil.Process().children()
    finally:
        began = time.monotonic()
        closer.close()
    gone, alive = psutil.wait_procs(workers, timeout=PROCESS_GONE_TIMEOUT_S)
    assert not alive, f"the check's process still runs {PROCESS_GONE_TIMEOUT_S:g} s after close()"
    assert time.monotonic() - began < PROCESS_GONE_TIMEOUT_S
    assert closer.take_done(chain) == []  # abandoned: no verdict
