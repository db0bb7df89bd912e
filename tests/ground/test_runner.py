"""The station's threads (runner.py): the mesher keeps only each submap's newest request, and a
restarted drone's new map never takes the place of its old map's last mesh."""
from __future__ import annotations

import threading

import numpy as np

from kinfly_ground.runner import Runner

# Long enough for a loaded machine to start the mesher thread; it is a bound, not a wait.
MESHER_START_TIMEOUT_S = 30.0


class _Snapshot:
    def __init__(self, name: str) -> None:
        self.name = name

    def mesh(self) -> tuple[str, np.ndarray, None]:
        return self.name, np.zeros((0, 3), np.int32), None


class _View:
    """Records what was meshed; the first mesh holds the mesher until released, so the requests
    made meanwhile wait together."""

    def __init__(self) -> None:
        self.meshed: list[str] = []
        self.first_entered = threading.Event()
        self.release = threading.Event()

    def mesh(self, utime: int, submap: int, name: str, triangles: np.ndarray,
             normals: None) -> None:
        if not self.meshed:
            self.first_entered.set()
            self.release.wait()
        self.meshed.append(name)


class _Vehicle:
    def __init__(self) -> None:
        self.vehicle_id = 1
        self.finished_segments: list[object] = []
        self.view = _View()


def test_the_mesher_keeps_each_submaps_newest_and_a_restarted_maps_apart() -> None:
    runner: Runner[object] = Runner(4, lambda job: None, lambda job: None, inline=False,
                                    log=print)
    vehicle = _Vehicle()
    try:
        runner.mesh(vehicle, 1, 0, _Snapshot("first"))
        assert vehicle.view.first_entered.wait(MESHER_START_TIMEOUT_S)
        runner.mesh(vehicle, 2, 1, _Snapshot("submap 1, older"))
        runner.mesh(vehicle, 3, 1, _Snapshot("submap 1, newer"))
        # The drone restarted: its new map's submap 1 is another map's.
        vehicle.finished_segments.append(object())
        runner.mesh(vehicle, 4, 1, _Snapshot("new map's submap 1"))
    finally:
        vehicle.view.release.set()
        runner.stop()  # meshes whatever waits, then returns
    assert vehicle.view.meshed == ["first", "submap 1, newer", "new map's submap 1"]
