"""The station's threads (docs/ground.md, "Threads and memory"): a bounded queue of keyframes, one
worker thread that handles them one at a time (and runs requests, such as an export, between
them), and a low-priority mesher thread that meshes a map every few seconds (only the blocks
changed since its last mesh and their neighbours, copied on the fusion thread), so marching cubes
never holds up a correction. Inline (replay) everything runs on the caller's thread: every keyframe, nothing
dropped.

Queue policy: at most `capacity` keyframes wait. When a new one arrives to a full queue the oldest
waiting one is dropped (and handed to `on_drop` to be counted): a station that stays slower than
the drone can only keep up by dropping, and the newest keyframe, whose correction is freshest, is
the one to keep."""
from __future__ import annotations

import collections
import os
import threading
import time
from collections.abc import Callable
from typing import Any, Generic, TypeVar

Job = TypeVar("Job")


class Runner(Generic[Job]):
    """PROCESS handles one job on the worker thread (it must not raise); ON_DROP is told of a job
    pushed out of the full queue."""

    def __init__(self, capacity: int, process: Callable[[Job], None],
                 on_drop: Callable[[Job], None], *, inline: bool,
                 log: Callable[[str], None]) -> None:
        self._capacity = capacity
        self._process = process
        self._on_drop = on_drop
        self._inline = inline
        self._log = log
        self._queue: collections.deque[Job] = collections.deque()
        self._cv = threading.Condition()
        self._stopping = False
        self._idle = True
        # (vehicle state, capture time, submap index, snapshot) by (vehicle, map, submap), the
        # map being the vehicle's count of maps it restarted from: only each submap's latest
        # waits, and a closed submap's last mesh is never replaced, not even by the submap of
        # that index in the map a restarted drone begins.
        self._mesh_jobs: dict[tuple[int, int, int], tuple[Any, int, int, Any]] = {}
        self._mesh_cv = threading.Condition()
        self._threads: list[threading.Thread] = []
        self._export_requests: list[Callable[[], None]] = []
        if not inline:
            self._threads = [threading.Thread(target=self._work, name="kground-fuse", daemon=True),
                             threading.Thread(target=self._mesh_loop, name="kground-mesh",
                                              daemon=True)]
            for thread in self._threads:
                thread.start()

    def submit(self, job: Job) -> None:
        """Queues JOB for the worker (inline: handles it now)."""
        if self._inline:
            self._process(job)
            return
        with self._cv:
            if len(self._queue) >= self._capacity:
                self._on_drop(self._queue.popleft())
            self._queue.append(job)
            self._cv.notify()

    def mesh(self, state: Any, utime: int, submap: int, snapshot: Any) -> None:
        """Meshes SNAPSHOT of STATE's submap SUBMAP for its view on the mesher thread (inline:
        now); a newer request for the same submap replaces one still waiting."""
        if self._inline:
            state.view.mesh(utime, submap, *snapshot.mesh())
            return
        with self._mesh_cv:
            key = (state.vehicle_id, len(state.finished_segments), submap)
            self._mesh_jobs.pop(key, None)  # the newer goes last, in the order asked
            self._mesh_jobs[key] = (state, utime, submap, snapshot)
            self._mesh_cv.notify()

    def _work(self) -> None:
        while True:
            with self._cv:
                while not self._queue and not self._export_requests and not self._stopping:
                    self._idle = True
                    self._cv.notify_all()
                    self._cv.wait()
                if self._export_requests:
                    request = self._export_requests.pop(0)
                    job = None
                elif self._queue:
                    job = self._queue.popleft()
                    request = None
                else:
                    self._idle = True
                    self._cv.notify_all()
                    return
                self._idle = False
            if request is not None:
                try:
                    request()
                except Exception as error:  # an export on request: fusion goes on regardless
                    self._log(f"request failed: {type(error).__name__}: {error}")
            else:
                self._process(job)

    def _mesh_loop(self) -> None:
        # Niceness is per thread on Linux: fusion keeps the cores while a mesh is made.
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        except OSError:
            pass
        while True:
            with self._mesh_cv:
                while not self._mesh_jobs and not self._stopping:
                    self._mesh_cv.wait()
                if not self._mesh_jobs:
                    return
                state, utime, submap, snapshot = self._mesh_jobs.pop(next(iter(self._mesh_jobs)))
            try:
                state.view.mesh(utime, submap, *snapshot.mesh())
            except Exception as error:  # a mesh is for display: fusion goes on without it
                self._log(f"vehicle {state.vehicle_id}: no mesh for the viewer: {error}")

    def run_in_worker(self, request: Callable[[], None]) -> None:
        """Runs REQUEST on the fusion thread between keyframes (an export on request), where the
        maps are not being changed."""
        if self._inline:
            request()
            return
        with self._cv:
            self._export_requests.append(request)
            self._cv.notify()

    def drain(self, timeout_s: float) -> bool:
        """Waits until every queued keyframe is fused; False when TIMEOUT_S passed first."""
        if self._inline:
            return True
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while self._queue or self._export_requests or not self._idle:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
        return True

    def stop(self) -> None:
        with self._cv:
            self._stopping = True
            self._cv.notify_all()
        with self._mesh_cv:
            self._mesh_cv.notify_all()
        for thread in self._threads:
            thread.join()

    def queue_length(self) -> int:
        return len(self._queue)
