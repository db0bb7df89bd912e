"""A vehicle's map as a chain of submaps (issue 17 §2, after voxgraph and c-blox): each submap is
a hashed volume of its own, fused from consecutive keyframes and closed after a distance, a time
or keyframes that failed to register; the submaps are the nodes of a pose graph, and a loop
closure moves whole submaps (their meshes with them) instead of integrating anything again.

Frames. Every submap is fused in the chain's frame `c`, the world the first keyframe was fused
in (as a single map was), starting at the pose the chain had reached:
submap k's anchor A_k = T_c_anchor is its first keyframe's pose there. The optimised graph places
the anchors at O_k = T_world_anchor; submap k's correction C_k = O_k A_k⁻¹ takes its content
(and its keyframes' poses) from `c` into the optimised world. Before any loop every C_k is the
identity and the chain is the single map of before. Where another vehicle's map was found in
this one's (merge.py), the whole optimised world is placed in the shared one by W = T_shared_world
(`place`): every correction handed out, C_k's included, is then W C_k; the graph itself stays in
the chain's own world, its first submap held.

Threads. `refine`, `close_if_due`, `loop_candidates` and `add_loops` (a graph of tens of nodes:
milliseconds) run on the fusion thread, the only one that changes the chain. `check_arguments` meshes closed submaps, whose snapshots do
not change, and may run anywhere (loops.py checks them off the keyframe path); `correction`,
`trajectory` and `mesh` read the corrections under a lock."""
from __future__ import annotations

import collections
import dataclasses
import math
import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.stats

from ._native import Fusion, MapSnapshot, TrackingStatus, rotation_angle_rad
from .posegraph import EdgeSigma, PoseGraph
from .registration import LoopCheck, RegistrationParams, check_loop

StampedPose = tuple[int, np.ndarray]  # (utime [us], 4x4)


@dataclasses.dataclass(frozen=True)
class SubmapParams:
    # A submap closes once the camera travelled this far in it, or this long in capture time
    # (3 m and 30 s hold a room's worth of surface for registration, and keep a submap's own
    # drift under the loop check's residual gate). Off unless asked for: in a room the drone
    # keeps in view, registering every keyframe against one map already closes the loop, and a
    # chain closed by distance or time maps the room again and again (`make sim`'s room tour
    # replayed: 0.11 cm ATE and 398 MB as one map, 0.17 cm and 789 MB with 3 m and 30 s; the
    # five-minute three laps: 0.17 cm both, 396 against 2306 MB; docs/ground.md). Until a close
    # rule that keeps a room one map is measured, a submap closes on its own only where
    # keyframes stop registering (new_after_lost).
    max_distance_m: float = math.inf
    max_duration_s: float = math.inf
    # A submap begun at a close also holds the closed one's last keyframes, fused at their
    # refined poses: a map of one keyframe is too thin for the next to register against
    # (`make sim`'s room tour, replayed: inlier fractions of 0.07-0.10 after each close, 0.1
    # required, and 7 of 153 keyframes lost; with the last 4 overlapping, one keyframe at 0.097
    # six after a close; with 8, about 0.8 m of flight, none).
    overlap_keyframes: int = 8
    # This many keyframes in a row that do not register start a new submap at the drone's pose:
    # the map no longer fits where the drone is (a long dropout, a new room).
    new_after_lost: int = 3
    # The odometry between consecutive submaps: the ground's refined chain drifts this much per
    # metre travelled in a submap, plus a floor. Where a submap began after lost keyframes, the
    # edge is the drone's own odometry across the gap, trusted less.
    drift_per_m: EdgeSigma = EdgeSigma(translation_m=0.02, rotation_rad=math.radians(1.0))
    drift_floor: EdgeSigma = EdgeSigma(translation_m=0.01, rotation_rad=math.radians(0.5))
    lost_gap: EdgeSigma = EdgeSigma(translation_m=0.2, rotation_rad=math.radians(10.0))
    # A loop's error as registered (registration.py's gates leave it well under these).
    loop: EdgeSigma = EdgeSigma(translation_m=0.01, rotation_rad=math.radians(0.5))
    # Closed submaps whose anchors lie within this of a newly closed one's, as the graph now
    # places them, are loop candidates; neighbours in the chain are joined by odometry already.
    loop_search_radius_m: float = 3.0
    min_loop_separation: int = 2
    # Each check registers two submaps (about a second): the nearest few are enough, a place
    # seen from several earlier submaps closes against one of them.
    max_loop_candidates: int = 3
    # A registration may move a candidate from the graph's guess only as far as the graph's
    # uncertainty between the two submaps allows (the odometry's sigmas along the chain between
    # them, and the loop's own): the move's chi-square over 6 degrees of freedom below this
    # probability's, as the graph's own inlier threshold (posegraph.py). On the TUM teddy
    # sample out and back, the first loop checked (two submaps a metre of chain apart, guessed
    # within 1 cm) registered 10.7 cm and 3.8 degrees off with overlap 0.54 and 7.5 mm, past
    # every gate of the check; once accepted it made the graph's next guesses as wrong, their
    # registrations agreed with it, and the graph took them all (ATE 1.1 -> 3.6 cm).
    guess_gate_probability: float = 0.99
    registration: RegistrationParams = RegistrationParams()

    def __post_init__(self) -> None:
        if not (self.max_distance_m > 0 and self.max_duration_s > 0):
            raise ValueError(f"a submap's distance and duration must be positive: {self}")
        if (self.new_after_lost < 1 or self.min_loop_separation < 2
                or self.max_loop_candidates < 1 or self.overlap_keyframes < 0):
            raise ValueError("new_after_lost and max_loop_candidates must be at least 1, "
                             "min_loop_separation at least 2, overlap_keyframes at least 0: "
                             f"{self}")
        if not self.loop_search_radius_m > 0:
            raise ValueError(f"loop_search_radius_m must be positive: {self.loop_search_radius_m}")
        if not 0 < self.guess_gate_probability < 1:
            raise ValueError("guess_gate_probability must be in (0, 1): "
                             f"{self.guess_gate_probability}")


@dataclasses.dataclass
class Submap:
    index: int
    T_c_anchor: np.ndarray          # A_k: its first keyframe's pose in the chain's frame
    first_utime: int
    fusion: Fusion | None           # None once closed
    snapshot: MapSnapshot | None = None  # the closed map, meshed for loops and outputs
    keyframes: list[StampedPose] = dataclasses.field(default_factory=list)  # T_c_cam refined
    path_m: float = 0.0
    began_after_loss: bool = False
    closed_memory_bytes: int = 0
    # Capture times of every keyframe fused into it, the overlap's included: two submaps that
    # share one are not a loop (their registration would count the odometry twice).
    fused_utimes: set[int] = dataclasses.field(default_factory=set)
    _points: np.ndarray | None = None

    def points(self) -> np.ndarray:
        """Its surface (mesh vertices) in the chain's frame; closed submaps only."""
        if self.snapshot is None:
            raise RuntimeError(f"submap {self.index} is still open")
        if self._points is None:
            vertices, _, _ = self.snapshot.mesh()
            self._points = np.asarray(vertices, dtype=np.float64)
        return self._points


@dataclasses.dataclass(frozen=True)
class LoopCandidate:
    older: int                    # submap indices
    newer: int
    T_older_newer_guess: np.ndarray  # content of `newer` into `older`'s, both in the chain frame
    # How far off the guess may be: the odometry's sigmas along the chain between the two and
    # the loop's, combined; None: any registration is plausible.
    guess_sigma: EdgeSigma | None = None


@dataclasses.dataclass(frozen=True)
class LoopOutcome:
    candidate: LoopCandidate
    check: LoopCheck
    accepted_by_graph: bool  # False where the check refused it, or the graph did


@dataclasses.dataclass(frozen=True)
class LoopsAdded:
    new: list[LoopOutcome]      # the checks just added, with the graph's verdicts
    # Earlier loops whose verdict this optimisation changed, as they now stand: the graph weighs
    # every loop again each time, and loops added since can out-vote one it took (or vouch for
    # one it refused).
    revised: list[LoopOutcome]


Mesh = tuple[np.ndarray, np.ndarray, np.ndarray]  # vertices Nx3, triangles Mx3, normals Nx3


def joined_meshes(meshes: list[Mesh]) -> Mesh:
    """MESHES as one (vertices float32, triangles int32, normals float32): each one's triangles
    numbered after the vertices of those before it."""
    if not meshes:
        return (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32),
                np.zeros((0, 3), np.float32))
    triangles, offset = [], 0
    for v, t, _ in meshes:
        triangles.append(np.asarray(t, np.int32) + np.int32(offset))
        offset += len(v)
    return (np.concatenate([np.asarray(v, np.float32) for v, _, _ in meshes]),
            np.concatenate(triangles),
            np.concatenate([np.asarray(n, np.float32) for _, _, n in meshes]))


class SubmapChain:
    """MAKE_FUSION makes an empty map for a new submap (the station's camera and parameters)."""

    def __init__(self, params: SubmapParams, make_fusion: Callable[[], Fusion]) -> None:
        self.params = params
        self._make_fusion = make_fusion
        self.submaps: list[Submap] = []
        self._edges: list[tuple[int, int, np.ndarray, EdgeSigma]] = []  # odometry
        self._loops: list[tuple[LoopCandidate, np.ndarray]] = []  # accepted checks, anchor edge
        self.outcomes: list[LoopOutcome] = []
        self._corrections: list[np.ndarray] = []  # C_k, swapped whole under the lock
        self._placement = np.eye(4)  # W: the optimised world in the shared one (under the lock)
        self._lock = threading.Lock()
        self._lost_in_a_row = 0
        # The world the drone's published pose is in: the C of the last correction it was sent
        # (correction_sent), and the one before, for keyframes it captured before that arrived.
        # The identity while it was sent none (a replay, a vehicle without a key). Each with the
        # placement W it held.
        self._C_returned = np.eye(4)  # of the last pose refine() returned
        self._C_sent = np.eye(4)
        self._C_sent_before = np.eye(4)
        self._W_returned = np.eye(4)
        self._W_sent = np.eye(4)
        self._W_sent_before = np.eye(4)
        # The placement of the world the last keyframe's guess was taken from (refine): its
        # published pose, taken back into the chain's own world, is W⁻¹ T.
        self.guess_placement = np.eye(4)
        # That published pose moved into the world of the correction before this one (the
        # drone's world once it applied that): a correction's jump is measured from there, so
        # that a keyframe captured before the drone applied a loop's or a merge's correction
        # does not count the same jump again.
        self.guess_moved = np.eye(4)
        # The open submap's last registered keyframes (utime, depth, T_c_cam), the overlap of
        # the next.
        self._recent: collections.deque[tuple[int, np.ndarray, np.ndarray]] = collections.deque(
            maxlen=params.overlap_keyframes + 1)

    @property
    def active(self) -> Submap | None:
        return self.submaps[-1] if self.submaps else None

    def correction(self, index: int) -> np.ndarray:
        """Submap INDEX's correction into the shared world: W C_k."""
        with self._lock:
            return self._placement @ self._corrections[index]

    def corrections(self) -> dict[int, np.ndarray]:
        """Every submap's W C_k by index."""
        with self._lock:
            return {k: self._placement @ C for k, C in enumerate(self._corrections)}

    @property
    def placement(self) -> np.ndarray:
        """W: the chain's optimised world in the shared one (the identity until merged)."""
        with self._lock:
            return self._placement.copy()

    def place(self, T_shared_world: np.ndarray) -> None:
        """Places the optimised world in a shared one (a merge with another vehicle's map): the
        next correction carries the move to the drone."""
        with self._lock:
            self._placement = np.array(T_shared_world, dtype=np.float64)

    def own_corrections(self) -> dict[int, np.ndarray]:
        """Every submap's C_k, in the chain's own optimised world (what a merge registers)."""
        with self._lock:
            return dict(enumerate(self._corrections))

    def refine(self, depth: np.ndarray, utime: int, T_world_guess: np.ndarray
               ) -> tuple[Any, np.ndarray | None, Submap | None]:
        """Registers a keyframe in the active submap and fuses it. T_WORLD_GUESS is the drone's
        published pose, which it moves with every correction it applies (docs/firmware.md,
        "Corrections"): in the world of the last correction sent (correction_sent), taken back
        into the chain's frame by that correction's C; where that fails and the correction
        before had another C (a loop came between), from that one, as a keyframe captured
        before the last correction arrived is. The first keyframe begins the chain, fused at
        the guess.
        Returns the engine's result, the keyframe's pose in the optimised world (None when it
        did not register), and the submap that closed because keyframes stopped registering
        (None otherwise)."""
        active = self.active
        if active is None:
            result = self._begin(depth, utime, T_world_guess, after_loss=False)
            return result, (result.T_world_cam if self.submaps else None), None
        T_c_guess = np.linalg.inv(self._C_sent) @ T_world_guess
        with self._lock:
            C, W = self._placement @ self._corrections[active.index], self._placement.copy()
        result = active.fusion.refine(depth, utime, T_c_guess)
        self.guess_placement = self._W_sent
        self.guess_moved = self._C_returned @ np.linalg.inv(self._C_sent)
        if (result.status is TrackingStatus.LOST
                and not np.array_equal(self._C_sent_before, self._C_sent)):
            retry = active.fusion.refine(depth, utime,
                                         np.linalg.inv(self._C_sent_before) @ T_world_guess)
            if retry.status is not TrackingStatus.LOST:
                result = retry
                self.guess_placement = self._W_sent_before
                self.guess_moved = self._C_returned @ np.linalg.inv(self._C_sent_before)
        if result.status in (TrackingStatus.FIRST_FRAME, TrackingStatus.OK):
            self._lost_in_a_row = 0
            T_c_cam = result.T_world_cam
            if active.keyframes:
                step = T_c_cam[:3, 3] - active.keyframes[-1][1][:3, 3]
                active.path_m += float(np.linalg.norm(step))
            active.keyframes.append((utime, T_c_cam))
            active.fused_utimes.add(utime)
            self._recent.append((utime, depth, T_c_cam))
            self._C_returned, self._W_returned = C, W
            return result, C @ T_c_cam, None
        self._lost_in_a_row += 1
        if self._lost_in_a_row < self.params.new_after_lost:
            return result, None, None
        # The map no longer fits where the drone is: begin again at its pose, with this
        # keyframe, where it has depth to begin with.
        count = len(self.submaps)
        began = self._begin(depth, utime, T_c_guess, after_loss=True)
        if len(self.submaps) == count:
            return result, None, None
        self._lost_in_a_row = 0
        self._C_returned, self._W_returned = C, W
        return began, C @ began.T_world_cam, active

    def correction_sent(self) -> None:
        """The pose refine() last returned went to the drone as a correction: its published
        poses move into that pose's world."""
        if not np.array_equal(self._C_returned, self._C_sent):
            self._C_sent_before, self._C_sent = self._C_sent, self._C_returned
            self._W_sent_before, self._W_sent = self._W_sent, self._W_returned

    def last_pose_published(self) -> np.ndarray:
        """The last registered keyframe's pose in the world the drone's published poses are in
        (the last correction sent), the guess for a keyframe without an onboard pose; the
        identity before the first."""
        active = self.active
        if active is None:
            return np.eye(4)
        return self._C_sent @ active.keyframes[-1][1]

    @property
    def num_blocks(self) -> int:
        """Blocks allocated in every submap's volume (closed ones' as they closed)."""
        return sum(s.fusion.num_blocks if s.fusion is not None else s.snapshot.num_blocks
                   for s in self.submaps)

    @property
    def memory_bytes(self) -> int:
        """The open submap's volume and the closed ones' volumes as they closed: a closed
        volume is freed, but its blocks live on in its snapshot until meshed."""
        return sum(s.fusion.memory_bytes if s.fusion is not None else s.closed_memory_bytes
                   for s in self.submaps)

    def close_if_due(self, depth: np.ndarray, utime: int) -> Submap | None:
        """After the keyframe's correction has gone out: where the active submap has travelled
        or lasted long enough, closes it and begins the next with the same keyframe at its
        refined pose, its map overlapping the closed one's last `overlap_keyframes`. Returns the
        closed submap (for the loop search), else None."""
        active = self.active
        if active is None or active.keyframes[-1][0] != utime:
            return None
        age_s = (utime - active.first_utime) * 1e-6
        if active.path_m < self.params.max_distance_m and age_s < self.params.max_duration_s:
            return None
        overlap = [kf for kf in self._recent if kf[0] != utime]
        self._begin(depth, utime, active.keyframes[-1][1], after_loss=False)
        if self.active is active:  # too little depth to begin a map with: it stays open
            return None
        for kf_utime, kf_depth, T_c_cam in overlap:
            self.active.fusion.fuse_at(kf_depth, kf_utime, T_c_cam)
            self.active.fused_utimes.add(kf_utime)
        return active

    def _begin(self, depth: np.ndarray, utime: int, T_c_cam: np.ndarray, after_loss: bool) -> Any:
        """A new submap whose first keyframe is fused at T_c_cam; the one before is closed.
        Nothing changes where the keyframe has too little depth to begin a map with."""
        fusion = self._make_fusion()
        result = fusion.refine(depth, utime, T_c_cam)
        if result.status is not TrackingStatus.FIRST_FRAME:
            return result
        anchor = result.T_world_cam
        self._recent.clear()
        self._recent.append((utime, depth, anchor))
        submap = Submap(len(self.submaps), anchor, utime, fusion, keyframes=[(utime, anchor)],
                        began_after_loss=after_loss, fused_utimes={utime})
        previous = self.active
        if previous is not None:
            previous.snapshot = previous.fusion.snapshot()
            previous.closed_memory_bytes = previous.fusion.memory_bytes
            previous.fusion = None
        with self._lock:
            if previous is not None:
                self._edges.append((previous.index, submap.index,
                                    np.linalg.inv(previous.T_c_anchor) @ anchor,
                                    self._odometry_sigma(previous, after_loss)))
            # It continues its predecessor's frame, so its correction too.
            self._corrections.append(self._corrections[-1] if self._corrections else np.eye(4))
            self.submaps.append(submap)
        return result

    def _odometry_sigma(self, previous: Submap, after_loss: bool) -> EdgeSigma:
        if after_loss:
            return self.params.lost_gap
        p = self.params
        return EdgeSigma(p.drift_floor.translation_m + p.drift_per_m.translation_m * previous.path_m,
                         p.drift_floor.rotation_rad + p.drift_per_m.rotation_rad * previous.path_m)

    def loop_candidates(self, closed: Submap) -> list[LoopCandidate]:
        """Closed submaps near CLOSED as the graph now places them, the nearest few first."""
        with self._lock:
            corrections = list(self._corrections)
        position = (corrections[closed.index] @ closed.T_c_anchor)[:3, 3]
        found = []
        with self._lock:
            earlier = self.submaps[: max(0, closed.index - self.params.min_loop_separation + 1)]
        for other in earlier:
            if other.snapshot is None or other.fused_utimes & closed.fused_utimes:
                continue
            distance = np.linalg.norm((corrections[other.index] @ other.T_c_anchor)[:3, 3]
                                      - position)
            if distance <= self.params.loop_search_radius_m:
                guess = np.linalg.inv(corrections[other.index]) @ corrections[closed.index]
                found.append((distance, LoopCandidate(other.index, closed.index, guess,
                                                      self._guess_sigma(other.index,
                                                                        closed.index))))
        nearest = sorted(found, key=lambda pair: pair[0])[: self.params.max_loop_candidates]
        return [candidate for _, candidate in nearest]

    def _guess_sigma(self, older: int, newer: int) -> EdgeSigma:
        """The odometry edges' sigmas from OLDER to NEWER and the loop's, summed in squares."""
        with self._lock:
            edges = [sigma for i, _, _, sigma in self._edges if older <= i < newer]
        squares = [(s.translation_m**2, s.rotation_rad**2) for s in [*edges, self.params.loop]]
        return EdgeSigma(math.sqrt(sum(t for t, _ in squares)),
                         math.sqrt(sum(r for _, r in squares)))

    def _within_guess(self, candidate: LoopCandidate, check: LoopCheck) -> LoopCheck:
        """CHECK, refused where its registration moved further from the guess than the guess's
        uncertainty allows."""
        sigma = candidate.guess_sigma
        if not check.accepted or sigma is None:
            return check
        # The edge as registered against the edge as guessed, in the newer anchor's frame, as
        # the sigmas are: in the chain's frame a turn would count its lever arm to the origin.
        move = (np.linalg.inv(self._loop_edge(candidate, candidate.T_older_newer_guess))
                @ self._loop_edge(candidate, check.T_target_source))
        translation_m = float(np.linalg.norm(move[:3, 3]))
        rotation_rad = rotation_angle_rad(move)
        # Isotropic sigmas: three translation and three rotation components.
        chi_square = ((translation_m / sigma.translation_m)**2
                      + (rotation_rad / sigma.rotation_rad)**2)
        limit = float(scipy.stats.chi2.ppf(self.params.guess_gate_probability, 6))
        if chi_square <= limit:
            return check
        return dataclasses.replace(check, accepted=False, reason=(
            f"moved {100 * translation_m:.1f} cm and {math.degrees(rotation_rad):.1f} deg from "
            f"the graph's guess, beyond its uncertainty ({100 * sigma.translation_m:.1f} cm, "
            f"{math.degrees(sigma.rotation_rad):.1f} deg: chi-square {chi_square:.1f} > "
            f"{limit:.1f})"))

    def check_arguments(self, candidate: LoopCandidate
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, RegistrationParams]:
        """registration.check_loop's arguments for CANDIDATE: the two submaps' surfaces
        (meshing a closed submap the first time: tenths of a second, the GIL released)."""
        return (self.submaps[candidate.older].points(), self.submaps[candidate.newer].points(),
                candidate.T_older_newer_guess, self.params.registration)

    def check(self, candidate: LoopCandidate) -> LoopCheck:
        """Registers the two submaps' surfaces in this thread (seconds, the GIL held)."""
        return check_loop(*self.check_arguments(candidate))

    def add_loops(self, checked: list[tuple[LoopCandidate, LoopCheck]]) -> LoopsAdded:
        """Adds the loops that passed their check to the graph, optimises it and swaps every
        submap's correction. Returns each new loop's outcome and the earlier ones whose verdict
        changed; `outcomes` keeps every loop's as it now stands. A check that moved its
        candidate further than the graph's uncertainty allows is refused first. Where the
        optimisation raises, nothing is kept: the graph stays as it was."""
        checked = [(candidate, self._within_guess(candidate, check))
                   for candidate, check in checked]
        loops = self._loops + [(candidate, self._loop_edge(candidate, check.T_target_source))
                               for candidate, check in checked if check.accepted]
        graph = PoseGraph()
        with self._lock:
            corrections = list(self._corrections)
        for submap in self.submaps:
            graph.add_node(submap.index, corrections[submap.index] @ submap.T_c_anchor)
        for i, j, T, sigma in self._edges:
            graph.add_odometry(i, j, T, sigma)
        for candidate, T in loops:
            graph.add_loop(candidate.older, candidate.newer, T, self.params.loop)
        result = graph.optimise()
        if len(result.loop_accepted) != len(loops):
            raise ValueError(f"the graph judged {len(result.loop_accepted)} loops of "
                             f"{len(loops)}")
        # The graph's verdicts follow its loops' order, which is the order of the outcomes whose
        # check passed, the earlier ones first (a pair of submaps may be tried more than once).
        verdicts = iter(result.loop_accepted)
        outcomes = [dataclasses.replace(o, accepted_by_graph=o.check.accepted and next(verdicts))
                    for o in self.outcomes]
        revised = [now for now, before in zip(outcomes, self.outcomes)
                   if now.accepted_by_graph != before.accepted_by_graph]
        new = [LoopOutcome(c, check, check.accepted and next(verdicts)) for c, check in checked]
        self._loops = loops
        self.outcomes = outcomes + new
        with self._lock:
            self._corrections = [result.poses[s.index] @ np.linalg.inv(s.T_c_anchor)
                                 for s in self.submaps]
        return LoopsAdded(new, revised)

    def _loop_edge(self, candidate: LoopCandidate, T_older_newer: np.ndarray) -> np.ndarray:
        """The graph's edge from the older submap's anchor to the newer's, of a registration
        T_OLDER_NEWER of their content (both in the chain's frame)."""
        return (np.linalg.inv(self.submaps[candidate.older].T_c_anchor) @ T_older_newer
                @ self.submaps[candidate.newer].T_c_anchor)

    def graph(self) -> tuple[dict[int, np.ndarray], list[tuple[int, int]],
                             list[tuple[int, int, bool]]]:
        """The pose graph as the viewer draws it: each submap's anchor position in the optimised
        world, the odometry edges, and the loop edges (older, newer, accepted by the graph)."""
        with self._lock:
            corrections = [self._placement @ C for C in self._corrections]
            edges = [(i, j) for i, j, _, _ in self._edges]
            submaps = list(self.submaps)
        nodes = {s.index: (corrections[s.index] @ s.T_c_anchor)[:3, 3] for s in submaps}
        loops = [(o.candidate.older, o.candidate.newer, o.accepted_by_graph)
                 for o in self.outcomes if o.check.accepted]
        return nodes, edges, loops

    def parts(self, shared: bool) -> list[tuple[MapSnapshot, np.ndarray]]:
        """Each submap's map (the open one's snapshot taken now: the fusion thread only) and its
        correction, placed in the shared world (SHARED) or in the chain's own optimised one."""
        with self._lock:
            W = self._placement if shared else np.eye(4)
            corrections = [W @ C for C in self._corrections]
            submaps = list(self.submaps)
        return [(s.snapshot if s.snapshot is not None else s.fusion.snapshot(),
                 corrections[s.index]) for s in submaps]

    def trajectory(self, shared: bool = True) -> list[StampedPose]:
        """Every registered keyframe's pose in the optimised world, placed in the shared one
        (SHARED) or not, by capture time (a keyframe that began a submap is in both; the newer
        submap's is kept)."""
        with self._lock:
            W = self._placement if shared else np.eye(4)
            corrections = [W @ C for C in self._corrections]
        poses: dict[int, np.ndarray] = {}
        for submap in self.submaps:
            for utime, T in submap.keyframes:
                poses[utime] = corrections[submap.index] @ T
        return sorted(poses.items(), key=lambda pose: pose[0])

    def mesh(self) -> Mesh:
        """The whole map's mesh in the optimised world: each submap's own mesh moved by its
        correction, placed in the shared world (vertices float32 Nx3, triangles int32 Mx3,
        normals float32 Nx3)."""
        moved = []
        for snapshot, C in self.parts(shared=True):
            v, t, n = snapshot.mesh()
            moved.append(((np.asarray(v, np.float64) @ C[:3, :3].T + C[:3, 3]).astype(np.float32),
                          t, (np.asarray(n, np.float64) @ C[:3, :3].T).astype(np.float32)))
        return joined_meshes(moved)
