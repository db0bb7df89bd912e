"""`make sim`: the drone flown in the simulated room through the real programs.

kinfly-sim (the world: dynamics, wind, IMU, the depth camera rendered by Embree) drives the native
kinfly-fw (depth over LCM, the motors backend, the IMU as its only clock) in lockstep, and kinfly-
ground maps the keyframes and sends its corrections, each keyframe's before the drone's next frame
(source.lockstep), so that a seed flies the same flight on any machine (but for a link loss, whose
nftables rule draws its own random numbers). Two lcm-loggers record the flight. They run in a
private network namespace, as `make demo` does, in two parts as on a drone: the simulator and
kinfly-fw share the drone's bus (LCM multicast: IMU, depth, rotor commands), and the drone and the
ground station talk over the link, kinfly's UDP unicast peers (docs/wire.md, "Unicast on Wi-Fi"),
each side on a multicast group and port of its own; the simulator sends the truth to the ground's
bus too, as a motion-capture system would. The simulator flies its mission (the room tour unless
told otherwise: take off, three go-tos, a figure eight, the go-tos again, land) and the run
succeeds only when the drone landed without a collision or a failsafe and the ground mapped what
it was sent. Nothing waits a fixed time: each program's readiness and end are what the next step
waits for. A mission's ground_restart and link_loss are this script's to act on: kinfly-sim
(--orchestrated) stops its clock at each kill, restart, loss start and end until told that it was
done, so each lasts exactly the mission's simulated time; the loss is an nftables rule on the
link's two UDP ports alone (scripts/netns.py), so the drone's bus stays whole.

Run with the project's .venv python (the Makefile does). Needs root or passwordless sudo for the
namespace (docs/sim.md)."""
from __future__ import annotations

import argparse
import json
import math
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from demo import (BUILD, FW_CONFIG, GROUND_EXIT_TIMEOUT_S, LCM_URL, VEHICLE_ID,  # noqa: E402
                  Watched, check_flight, fresh_output, ground_command, list_outputs, report,
                  start_ground)
from netns import (LinkShape, NetnsUnavailable, kill_group, link_counters,  # noqa: E402
                   network_namespace, send_signal, set_loss)
from sim_plots import kinfly_eval, write as write_plots  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
DRONE_EXIT_TIMEOUT_S = 60.0  # kinfly-fw's last corrections and its summary after SIGINT
MISSIONS = REPO_ROOT / "sim" / "missions"
HOVER = "hover"  # --mission: kinfly-sim's built-in take off, hold, land
# Scenes from the shared data (kinfly_eval.data_root): the mesh file, and where the drone stands
# on its floor (kinfly-sim --scene-start: x, y in the mesh's frame, heading in degrees), in an
# open stretch of floor with room to climb.
DATA_SCENES = {
    "office0": ("replica_office0_nvblox/replica/office0_mesh.ply", (0.4, -1.7, 90.0)),
}
# Each scene's mission unless --mission says otherwise.
SCENE_MISSIONS = {"room": MISSIONS / "room_tour.toml", "corridor": MISSIONS / "corridor.toml",
                  "ring": MISSIONS / "ring_loop.toml", "hall": MISSIONS / "look_around.toml",
                  "office0": MISSIONS / "office0.toml"}
# kinfly-sim's words after an event it waits on this script for (kAwaitingOrchestrator).
AWAITING = ": waiting for the orchestrator"
# The link: each side's UDP port for the other's unicast, and the ground's own LCM bus, on a
# port of its own: Debian's liblcm (kinfly-fw, kinfly-sim, lcm-logger) hears every group on its
# port, so a group apart on the same port would leak the ground's messages onto the drone's bus.
DRONE_PEER_PORT, GROUND_PEER_PORT = 7668, 7669
GROUND_LCM_URL = "udpm://239.255.76.68:7670?ttl=0"
# How long after its frame's capture each odometry pose reaches the drone's estimator, in simulated
# time: the camera's 30 ms latency and one frame at 30 Hz for the odometry, the budget a drone's
# must keep. kinfly-sim waits for a pose only then (--pose-age-ms) and kinfly-fw fuses it then
# (flight.lockstep_pose_age_s), so the odometry runs beside the simulator and a seed still flies
# the same flight on any machine (docs/sim.md, "Lockstep").
POSE_AGE_MS = 63
# The programs share the cores: OpenMP's threads spinning while they wait (libgomp's default) would
# take the cores from the others' work (docs/sim.md, "Lockstep").
SHARE_CORES = ["env", "OMP_WAIT_POLICY=PASSIVE"]
# The loss a mission's link_loss_started line asks for (kinfly-sim: "loss=0.2 run=4").
LOSS_SHAPE = re.compile(r"loss=([0-9.e+-]+) run=([0-9.e+-]+)")
OUTPUTS = {
    "sim_summary.json": "the simulator's figures: hover against truth, touchdown, collisions",
    "summary.json": "the ground station's: keyframes, corrections, ATE, memory",
    "session.rrd": "the rerun recording (open it with rerun)",
    "mesh.ply": "the ground's map of the room (binary PLY)",
    "trajectory_onboard.tum": "each keyframe's pose as the drone sent it",
    "trajectory_corrected.tum": "each keyframe's pose as the ground refined it",
    "trajectory_optimised.tum": "each keyframe's pose where the map's pose graph puts it at the end",
    "trajectory_ground_truth.tum": "the simulator's true camera poses",
    "flight.lcmlog": "the drone's bus but the raw depth (kinfly-ground replay reads it)",
    "ground.lcmlog": "what the ground station sent back: corrections, status, repair requests",
    "tracking.png": "position and attitude: truth, the drone's estimate, its setpoint",
    "errors.png": "the estimate's and the tracking's errors against truth",
    "flight_errors.json": "their RMS while airborne",
    "scene.ply": "the scene's mesh, the truth the map is scored against",
    "map_accuracy.json": "the map's vertices' distances to the scene's surface",
    "drone_trajectory.tum": "every pose the drone's odometry published",
    "vehicle.key": "the signing key made for this flight",
}
# What a killed ground station's recording becomes (its N-th kill); the restarted one records
# session.rrd anew.
KILLED_RECORDING = "session_until_kill_{}.rrd"
# The recording a station writes until it closes it (kinfly_ground.viewer.Viewer).
PARTIAL_RECORDING = "session.rrd.partial"


def recorded(vehicle: int) -> str:
    """What lcm-logger records on the drone's bus: everything but the raw depth frames (30 a
    second at VGA; the keyframes that reached the ground are in their chunks)."""
    return (f"KINFLY_{vehicle}_(IMU|MOTOR_COMMAND|SIM_STATE|ODOMETRY|KEYFRAME_CHUNK|STATUS|"
            "FLIGHT|COMMAND|GROUND_TRUTH)")


def recorded_ground(vehicle: int) -> str:
    """... and on the ground's: what the ground station sent back."""
    return f"KINFLY_{vehicle}_(GROUND_STATUS|CORRECTION|CHUNK_REQUEST)"


class Ground:
    """kinfly-ground in the namespace, killed and restarted as the mission says."""

    def __init__(self, netns: list[str], out: Path, key: Path, vehicle: int) -> None:
        self.command = [*netns, *SHARE_CORES,
                        *ground_command(out, key=key, vehicle=vehicle, lcm_url=GROUND_LCM_URL),
                        "--peer", f"127.0.0.1:{DRONE_PEER_PORT}", "--peer-port",
                        str(GROUND_PEER_PORT)]
        self.out = out
        self.kills = 0
        self.current: Watched | None = None  # None while it is down
        self.start()

    def start(self) -> None:
        if self.current is not None:
            raise RuntimeError("kinfly-sim asked for a second ground station beside the first")
        self.current = start_ground(self.command)

    def kill(self) -> None:
        """As a crash ends it: SIGKILL, no outputs but the recording so far, which is kept and
        made whole (rerun's footer) as KILLED_RECORDING."""
        if self.current is None:
            raise RuntimeError("kinfly-sim asked to kill a ground station that is down")
        kill_group(self.current.process)
        self.current.finish(GROUND_EXIT_TIMEOUT_S)
        self.current = None
        self.kills += 1
        partial = self.out / PARTIAL_RECORDING
        if not partial.is_file():
            return
        kept = self.out / KILLED_RECORDING.format(self.kills)
        with kept.open("wb") as whole:
            made = subprocess.run([str(Path(sys.executable).parent / "rerun"), "rrd", "optimize",
                                   str(partial)], stdout=whole, stderr=subprocess.PIPE, text=True)
        if made.returncode != 0:
            kept.unlink()
            partial.rename(kept.with_name(kept.name + ".partial"))
            raise RuntimeError(f"the killed ground station's recording could not be made whole "
                               f"(kept as {kept.name}.partial): {made.stderr.strip()}")
        partial.unlink()

    def stop(self) -> list[str]:
        """SIGTERM, as Ctrl-C: it writes its outputs. What went wrong, if anything."""
        if self.current is None:
            return [f"the flight ended with the ground station down (killed {self.kills} "
                    "time(s); its restart never came): it wrote no outputs"]
        send_signal(self.current.process, signal.SIGTERM)
        if self.current.finish(GROUND_EXIT_TIMEOUT_S) != 0:
            return ["kinfly-ground failed (above)"]
        return []


class Link:
    """The drone-ground link's loss as the mission says: an nftables rule on its two UDP ports,
    the drone's bus untouched."""

    def __init__(self, netns: list[str]) -> None:
        self.netns = netns
        self.shape: LinkShape | None = None
        self.losses: list[str] = []  # what each loss did

    def start(self, line: str) -> None:
        shape = LOSS_SHAPE.search(line)
        if shape is None:
            raise RuntimeError(f"kinfly-sim's link loss says no shape: {line.strip()}")
        self.shape = LinkShape(loss=float(shape[1]), loss_run_packets=float(shape[2]),
                               udp_ports=(DRONE_PEER_PORT, GROUND_PEER_PORT))
        set_loss(self.netns, self.shape)

    def end(self, line: str) -> None:
        self._end(f"until {line.split(': ')[1]}")

    def lift(self) -> None:
        """Ends a loss the flight outlived (it landed before the loss's end): the programs' last
        words then cross a whole link."""
        if self.shape is not None:
            self._end("lifted when the flight ended before the loss did")

    def _end(self, until: str) -> None:
        counts = link_counters(self.netns)
        set_loss(self.netns, None)
        label = self.shape.label() if self.shape else "?"
        self.losses.append(f"{label}: {counts['dropped']} of {counts['seen']} datagrams dropped "
                           f"({until})")
        self.shape = None


def act(line: str, ground: Ground, link: Link) -> None:
    """What kinfly-sim's LINE asks for."""
    for event, action in ((": ground_killed", lambda: ground.kill()),
                          (": ground_restarted", lambda: ground.start()),
                          (": link_loss_started", lambda: link.start(line)),
                          (": link_loss_ended", lambda: link.end(line))):
        if event in line:
            action()
            return
    raise RuntimeError(f"kinfly-sim waits for what sim.py cannot do: {line.strip()}")


def drone_command(key: Path, out: Path, camera_downsample: int, vehicle: int) -> list[str]:
    """kinfly-fw for the simulated Kinect at 1/CAMERA_DOWNSAMPLE of 640x480: its odometry at
    320x240 (the configuration's downsample of VGA), or at the camera's size when smaller."""
    width, height = 640 // camera_downsample, 480 // camera_downsample
    return [str(BUILD / "kinfly-fw"), "--config", str(FW_CONFIG), "--vehicle.id", str(vehicle),
            "--source.width", str(width), "--source.height", str(height),
            "--link.peers", f"127.0.0.1:{GROUND_PEER_PORT}", "--link.peer_port",
            str(DRONE_PEER_PORT),
            "--odometry.downsample", str(max(1, 2 // camera_downsample)),
            "--vehicle.key_file", str(key), "--link.lcm_url", LCM_URL, "--source.kind", "lcm",
            "--source.realtime", "false", "--source.lockstep", "true", "--flight.backend", "motors",
            "--flight.imu", "lcm", "--flight.lockstep", "true",
            "--flight.lockstep_pose_age_s", str(POSE_AGE_MS / 1000),
            # The engine's result does not depend on its threads (docs/sim.md, "Lockstep").
            "--odometry.threads", "2",
            "--output.trajectory", str(out / "drone_trajectory.tum")]


def scene_arguments(scene: str, start: list[float] | None = None, scale: float = 1.0,
                    scaled_to: Path | None = None) -> list[str]:
    """kinfly-sim's --scene (and --scene-start) for a scene of --scene: built in, or a mesh from
    the shared data, which must be there, with START (x, y, heading) or the scene's own. A mesh
    is scaled by SCALE about its origin, written to SCALED_TO (START is in the scaled frame)."""
    if scene not in DATA_SCENES:
        if scale != 1.0:
            raise ValueError(f"{scene}: only a mesh scene can be scaled (--scene-scale)")
        return ["--scene", scene, *([] if start is None else
                                    ["--scene-start", *(str(v) for v in start)])]
    mesh, scene_start = DATA_SCENES[scene]
    path = kinfly_eval.data_root() / mesh
    if not path.is_file():
        raise ValueError(f"{scene}: no mesh at {path} (the shared data: set KINFLY_DATA)")
    if scale != 1.0:
        if start is None:
            raise ValueError(f"{scene} scaled by {scale:g} needs --scene-start (its own start "
                             "need not be open floor any more)")
        if not 0.5 <= scale <= 4.0:
            raise ValueError(f"--scene-scale must be in [0.5, 4], got {scale:g}")
        if scaled_to is None:
            raise ValueError(f"{scene} scaled by {scale:g}: nowhere to write the scaled mesh")
        path = scaled_to
    start = scene_start if start is None else start
    return ["--scene", str(path), "--scene-start", *(str(v) for v in start)]


def write_scaled_scene(scene: str, scale: float, scaled_to: Path) -> None:
    """The mesh of SCENE scaled by SCALE about its origin, written to SCALED_TO, where
    scene_arguments pointed kinfly-sim."""
    import trimesh  # only here: the unscaled scenes need no mesh library
    scaled = trimesh.load(kinfly_eval.data_root() / DATA_SCENES[scene][0], process=False)
    scaled.apply_scale(scale)
    scaled.export(scaled_to)


def sim_command(key: Path, out: Path, args: argparse.Namespace, scene: list[str]) -> list[str]:
    return [str(BUILD / "kinfly-sim"), "--key-file", str(key), "--vehicle", str(args.vehicle),
            "--lcm-url", LCM_URL, *scene, "--seed", str(args.seed), "--pose-age-ms",
            str(POSE_AGE_MS),
            "--hover-s", str(args.hover_s), "--camera-downsample", str(args.camera_downsample),
            "--summary", str(out / "sim_summary.json"), "--scene-mesh", str(out / "scene.ply"),
            "--truth-lcm-url", GROUND_LCM_URL, "--orchestrated",
            *([] if args.mission == HOVER else ["--mission", str(args.mission)])]


def stop_all(sim: Watched | None, drone: Watched | None, ground: Ground | None,
             loggers: list[subprocess.Popen]) -> list[str]:
    """Ends every program, each whatever happened to the others (a simulator still running is
    stopped by a failure here): what went wrong."""
    def stop_sim() -> list[str]:
        if sim is not None and sim.process.poll() is None:
            kill_group(sim.process)
            sim.finish(DRONE_EXIT_TIMEOUT_S)
        return []

    def stop_drone() -> list[str]:
        if drone is None:
            return []
        send_signal(drone.process, signal.SIGINT)
        rc = drone.finish(DRONE_EXIT_TIMEOUT_S)
        return [f"kinfly-fw exited {rc}"] if rc != 0 else []

    def stop_loggers() -> list[str]:
        for logger in loggers:
            send_signal(logger, signal.SIGINT)
        for logger in loggers:
            logger.wait(10)
        return []

    steps: list[tuple[str, Callable[[], list[str]]]] = [
        ("kinfly-sim", stop_sim), ("kinfly-fw", stop_drone),
        ("kinfly-ground", ground.stop if ground is not None else lambda: []),
        ("lcm-logger", stop_loggers)]
    problems = []
    for name, step in steps:
        try:
            problems += step()
        except (OSError, subprocess.TimeoutExpired) as error:
            problems.append(f"stopping {name}: {error}")
    return problems


def missed_while_away(out: Path, ground: Ground | None, vehicle_id: int) -> int:
    """Keyframes the ground station may have missed: none, unless it was restarted; then those
    before the first one the restarted station heard (the killed one's map died with it)."""
    summary = out / "summary.json"
    if ground is None or not ground.kills or not summary.is_file():
        return 0
    vehicle = json.loads(summary.read_text())["vehicles"].get(str(vehicle_id), {})
    return vehicle.get("first_keyframe_id") or 0


def main() -> int:
    # SIGTERM (a test's or a bench's timeout) unwinds as an error would: every program is stopped
    # and the namespace deleted.
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "sim")
    p.add_argument("--scene", default="room", choices=list(SCENE_MISSIONS),
                   help="room, corridor, ring, hall (kinfly-sim's own) or office0 (Replica's scan "
                   "in the shared data: $KINFLY_DATA, else <repo>/../shared/data); default room")
    p.add_argument("--seed", type=int, default=1, help="the simulator's seed (default 1)")
    p.add_argument("--hover-s", type=float, default=20.0,
                   help=f"seconds the drone holds at 1 m before it lands (default 20); "
                   f"--mission {HOVER} only")
    p.add_argument("--mission", default=None,
                   help=f"a mission file (sim/missions/, docs/sim.md), or {HOVER!r} for "
                   f"kinfly-sim's built-in take off, hold --hover-s, land (default: the "
                   f"scene's, {MISSIONS.relative_to(REPO_ROOT)}/"
                   f"<room_tour|corridor|ring_loop|look_around|office0>.toml)")
    p.add_argument("--camera-downsample", type=int, default=1, choices=range(1, 5),
                   help="the simulated Kinect at 1/N of 640x480 (default 1)")
    p.add_argument("--vehicle", type=int, default=VEHICLE_ID,
                   help=f"the drone's vehicle id, in every channel (default {VEHICLE_ID})")
    p.add_argument("--scene-start", type=float, nargs=3, metavar=("X", "Y", "HEADING"),
                   help="where on the floor the drone stands instead of the scene's start "
                   "(kinfly-sim --scene-start: a built-in scene's frame is z down, its heading "
                   "from +x towards +y; a mesh's is z up, counter-clockwise) [m, m, deg]")
    p.add_argument("--scene-scale", type=float, default=1.0,
                   help="a mesh scene (office0) scaled by this about its origin: a larger room "
                   "of the same shapes, written to <out>/scene_scaled.ply; needs --scene-start, "
                   "in the scaled frame (default 1)")
    args = p.parse_args()
    if args.mission is None:
        args.mission = str(SCENE_MISSIONS[args.scene])
    out = args.out
    scaled_to = out / "scene_scaled.ply"
    try:
        scene = scene_arguments(args.scene, args.scene_start, args.scene_scale, scaled_to)
    except ValueError as error:
        print(f"sim: --scene: {error}", file=sys.stderr)
        return 2
    key = fresh_output(out)
    if args.scene_scale != 1.0:
        write_scaled_scene(args.scene, args.scene_scale, scaled_to)
    started = time.monotonic()
    problems: list[str] = []
    try:
        with network_namespace("sim") as netns:
            logger = subprocess.Popen([*netns, "lcm-logger", "--quiet", "--lcm-url", LCM_URL,
                                       "--channel", recorded(args.vehicle), str(out / "flight.lcmlog")],
                                      stdout=subprocess.DEVNULL, start_new_session=True)
            ground_logger = subprocess.Popen(
                [*netns, "lcm-logger", "--quiet", "--lcm-url", GROUND_LCM_URL, "--channel",
                 recorded_ground(args.vehicle), str(out / "ground.lcmlog")],
                stdout=subprocess.DEVNULL, start_new_session=True)
            ground = drone = sim = None
            link = Link(netns)
            try:
                ground = Ground(netns, out, key, args.vehicle)
                drone = Watched([*netns, *SHARE_CORES,
                                 *drone_command(key, out, args.camera_downsample,
                                                args.vehicle)],
                                "[drone]  ", quiet=False)
                sim = Watched([*netns, *SHARE_CORES, *sim_command(key, out, args, scene)],
                              "[sim]    ",
                              quiet=False, answered=True)
                acted = 0
                # The simulator waits after each such line: the latest is the one to act on.
                while sim.wait_for(AWAITING, acted + 1, math.inf):
                    act(sim.latest(AWAITING), ground, link)
                    sim.answer()
                    acted += 1
                sim_rc = sim.finish(None)
                link.lift()
                if sim_rc != 0:
                    problems.append(f"kinfly-sim exited {sim_rc}: the flight failed (above)")
            except (RuntimeError, ValueError, OSError, subprocess.TimeoutExpired) as error:
                problems.append(f"{type(error).__name__}: {error}")
            finally:
                problems += stop_all(sim, drone, ground, [logger, ground_logger])
    except NetnsUnavailable as error:
        print(f"sim: {error}", file=sys.stderr)
        return 1
    if drone is not None and "control: failsafe:" in drone.output():
        problems.append("a failsafe acted in flight (the drone's log above says which)")
    missed = missed_while_away(out, ground, args.vehicle)
    problems += check_flight(out, max_missing=missed, vehicle_id=args.vehicle)
    errors = None
    if (out / "flight.lcmlog").is_file():
        try:
            errors = write_plots(out, args.vehicle)
        except (OSError, ValueError, ImportError) as error:
            problems.append(f"no plots or map score: {error}")
    kills = 0 if ground is None else ground.kills
    killed = {KILLED_RECORDING.format(n): f"the recording of the ground station up to kill {n}"
              for n in range(1, kills + 1)}
    scaled = ({"scene_scaled.ply": "the mesh scene scaled (--scene-scale), as kinfly-sim loaded "
               "it"} if args.scene_scale != 1.0 else {})
    print(f"\nsim: {time.monotonic() - started:.0f} s; files in {out}:\n"
          f"{list_outputs(out, {**OUTPUTS, **killed, **scaled})}")
    for loss in link.losses:
        print(f"sim: link loss, {loss}")
    if kills and ground is not None and ground.current is not None:
        print(f"sim: the ground station was killed and restarted {kills} time(s); the last one "
              f"heard the drone from keyframe {missed} on, and its "
              f"outputs cover only that")
    problems += [f"{name} was not written" for name in OUTPUTS if not (out / name).is_file()]
    summary = out / "sim_summary.json"
    if summary.is_file():
        figures = json.loads(summary.read_text())
        hover = figures["hover_rms_m"]
        print(f"sim: hover RMS against truth "
              f"{'-' if hover is None else f'{hover * 100:.1f} cm'}, touchdown "
              f"{figures['touchdown_m_s']:.2f} m/s, {figures['failsafes']} failsafes, "
              f"{figures['real_time_factor']:.2f}x real time")
    if errors and errors["samples"]:
        print(f"sim: airborne {errors['airborne_s']:.0f} s: estimate against truth "
              f"{errors['estimator_position_rms_m'] * 100:.1f} cm, "
              f"{errors['estimator_velocity_rms_m_s'] * 100:.1f} cm/s, "
              f"{errors['estimator_tilt_rms_deg']:.2f}° RMS; setpoint against truth "
              f"{errors['tracking_rms_m'] * 100:.1f} cm RMS")
    if errors and "map" in errors:
        print(f"sim: the map against the scene: mean {errors['map']['mean_m'] * 1000:.1f} mm, "
              f"{errors['map']['outlier_fraction'] * 100:.1f} % of its vertices beyond "
              f"{kinfly_eval.MESH_INLIER_M * 100:.0f} cm")
    return report("sim", out, problems)


if __name__ == "__main__":
    sys.exit(main())
