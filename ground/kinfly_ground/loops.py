"""Loop checks off the keyframe path (issue 17 §2). When a submap closes, the fusion thread hands
its loop candidates here; a thread meshes the two submaps (marching cubes, the GIL released) and
registers them in a process of its own, because small_gicp holds the GIL for the whole
registration (a 1 ms thread waited 1.9 s beside 12 checks in-process; 25 ms beside a process:
docs/ground.md). The outcomes wait until the fusion thread takes them (`take_done`) and adds them
to its chain's graph between keyframes, so the chain only ever changes on that thread. Merge
checks between two vehicles' maps (merge.py: place recognition, then the same registration) take
the same thread and process, in turn with the loops (`submit_merge`, `take_merges`)."""
from __future__ import annotations

import concurrent.futures
import dataclasses
import multiprocessing
import os
import signal
import threading
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Protocol

from .registration import LoopCheck, check_loop
from .submaps import LoopCandidate, SubmapChain


# The check process runs beside fusion, which should keep most of the cores, but not at the
# lowest priority: beside a CI run's busy processes a check at niceness 19 got so little of a
# core that 4 of a replayed flight's 6 checks were still running a minute after its last
# keyframe, and at 10 the teddy chain's 12 checks took over a minute (a check is about a second
# of one core). At 5 (a third of a normal process's weight) beside two busy processes a check
# gets about a seventh of a core: a 5 minute flight's checks (3 per closed submap, one every
# 30 s) keep up.
CHECK_NICENESS = 5
# How soon close() stops the thread while a check runs.
CLOSE_POLL_S = 0.2


def _lower_priority() -> None:
    os.nice(CHECK_NICENESS)


class Job(Protocol):
    """Work for the check process: ARGUMENTS is called on the checks' thread (meshing there),
    FUNCTION then runs in the process with them (a module-level function: the process imports it
    by name)."""

    def arguments(self) -> tuple[Any, ...]: ...


@dataclasses.dataclass(frozen=True)
class _LoopJob:
    chain: SubmapChain
    candidate: LoopCandidate

    def arguments(self) -> tuple[Any, ...]:
        return self.chain.check_arguments(self.candidate)  # meshing: tenths of a second


@dataclasses.dataclass(frozen=True)
class CheckedMerge:
    job: Any                  # the job submitted (submit_merge)
    match: Any | None         # what its function returned; None where it failed (`error`)
    error: str = ""


@dataclasses.dataclass(frozen=True)
class CheckedLoop:
    chain: SubmapChain
    candidate: LoopCandidate
    check: LoopCheck | None   # None where the check failed (`error` says why)
    error: str = ""


class LoopCloser:
    """One thread and, from the first candidate on, one process. LOG reports a failed check;
    CHECK registers a candidate from the chain's check_arguments (a module-level function: the
    process imports it by name)."""

    def __init__(self, log: Callable[[str], None],
                 check: Callable[..., LoopCheck] = check_loop) -> None:
        self._log = log
        self._check_fn = check
        self._cv = threading.Condition()
        # (the job, the function the process runs it with), in the order submitted
        self._waiting: list[tuple[Job, Callable[..., Any]]] = []
        self._done: list[CheckedLoop] = []
        self._merges_done: list[CheckedMerge] = []
        self._busy = False
        self._closing = False
        self._executor: concurrent.futures.ProcessPoolExecutor | None = None
        self._worker_pid: int | None = None  # the executor's one process
        self._thread: threading.Thread | None = None

    def submit(self, chain: SubmapChain, candidates: list[LoopCandidate]) -> None:
        self._submit([(_LoopJob(chain, candidate), self._check_fn) for candidate in candidates])

    def submit_merge(self, job: Job, function: Callable[..., Any]) -> None:
        """A merge check: FUNCTION(*JOB.arguments()) in the process; its outcome comes back
        from take_merges."""
        self._submit([(job, function)])

    def _submit(self, jobs: list[tuple[Job, Callable[..., Any]]]) -> None:
        if not jobs:
            return
        with self._cv:
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="kground-loops",
                                                daemon=True)
                self._thread.start()
            self._waiting.extend(jobs)
            self._cv.notify_all()

    def take_done(self, chain: SubmapChain) -> list[CheckedLoop]:
        """The checks of CHAIN that finished since the last call."""
        with self._cv:
            mine = [done for done in self._done if done.chain is chain]
            self._done = [done for done in self._done if done.chain is not chain]
        return mine

    def take_merges(self) -> list[CheckedMerge]:
        """The merge checks that finished since the last call."""
        with self._cv:
            done, self._merges_done = self._merges_done, []
        return done

    def wait_idle(self, timeout_s: float) -> bool:
        """Waits until every submitted check finished; False when TIMEOUT_S passed first."""
        with self._cv:
            return self._cv.wait_for(lambda: not self._waiting and not self._busy, timeout_s)

    def close(self) -> None:
        """Stops the thread at once and ends the process: a check under way is abandoned. Left to
        finish it, the process would hold the station's exit until then (the executor's exit
        handler joins it): seconds, on a busy machine tens of seconds, after a Ctrl-C."""
        with self._cv:
            self._closing = True
            self._cv.notify_all()
            thread = self._thread
        if thread is not None:
            thread.join()
        if self._executor is not None and self._worker_pid is not None:
            # Ended before the executor lets it go: once reaped, its pid could be another's.
            try:
                os.kill(self._worker_pid, signal.SIGTERM)
            except ProcessLookupError:  # it had ended already
                pass
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)

    def _run(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._waiting or self._closing)
                if self._closing:
                    return
                job, function = self._waiting.pop(0)
                self._busy = True
            outcome: CheckedLoop | CheckedMerge | None = None
            try:
                result = self._check(job, function)
                if result is not None:  # None: closing
                    outcome = (CheckedLoop(job.chain, job.candidate, result)
                               if isinstance(job, _LoopJob) else CheckedMerge(job, result))
            except Exception as error:  # noqa: BLE001 - a failed check is no loop; fusion goes on
                why = f"{type(error).__name__}: {error}"
                if isinstance(job, _LoopJob):
                    outcome = CheckedLoop(job.chain, job.candidate, None, why)
                    self._log(f"loop check of submaps {job.candidate.older} and "
                              f"{job.candidate.newer} failed: {why}")
                else:
                    outcome = CheckedMerge(job, None, why)
                    self._log(f"merge check {job} failed: {why}")
            with self._cv:
                if isinstance(outcome, CheckedLoop):
                    self._done.append(outcome)
                elif outcome is not None:
                    self._merges_done.append(outcome)
                self._busy = False
                self._cv.notify_all()

    def _until_done(self, future: concurrent.futures.Future) -> bool:
        """Waits for FUTURE; False when close() came first."""
        while not future.done():
            concurrent.futures.wait([future], timeout=CLOSE_POLL_S)
            with self._cv:
                if self._closing:
                    return False
        return True

    def _start_process(self) -> bool:
        """The check process, started; False when close() came first."""
        # Spawned, not forked: the station's process has threads (LCM, fusion, rerun).
        executor = concurrent.futures.ProcessPoolExecutor(
            max_workers=1, mp_context=multiprocessing.get_context("spawn"),
            initializer=_lower_priority)
        try:
            # One worker, never replaced while the executor lives: close() ends it by its pid.
            started = executor.submit(os.getpid)
            if not self._until_done(started):
                executor.shutdown(wait=False, cancel_futures=True)
                return False
            self._worker_pid = started.result()
        except BrokenProcessPool:
            executor.shutdown(wait=False, cancel_futures=True)
            raise
        self._executor = executor
        return True

    def _check(self, job: Job, function: Callable[..., Any]) -> Any | None:
        """The check's outcome, or None when close() came first."""
        if self._executor is None and not self._start_process():
            return None
        assert self._executor is not None
        arguments = job.arguments()
        with self._cv:
            if self._closing:
                return None
        try:
            future = self._executor.submit(function, *arguments)
            return future.result() if self._until_done(future) else None
        except BrokenProcessPool:
            # The process died (killed for memory, say): the next check starts another.
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None
            self._worker_pid = None
            raise
