#!/usr/bin/env python3
"""kinfly's figure eight beside an independent oracle: RotorPy flying the same reference.

    .venv-bench/bin/python tests/bench/bench_flight_oracle.py
        [--flight-bench build/bin/kinfly-flight-bench] [--out out/bench] [--rate-hz 1000]
        [--no-aero]

Runs, in one go (issue 15):
  - kinfly-flight-bench, for kinfly's figure-eight position RMS: the whole flight stack on the
    test plant, flying on its estimator's state (noisy IMU, noisy 30 Hz poses 30 ms late);
  - kinfly-flight-bench --dump-figure-eight, for the reference itself: the minimum-snap figure
    eight (2 m x 1 m through 8 points, 1 m/s peak, then 1 s hold) sampled at every control tick;
  - RotorPy (PyPI rotorpy, .venv-bench only): its Hummingbird (the constants kinfly's
    VehicleParams defaults copy), its Multirotor, its SE3Control at its own gains on the true
    state, no wind, no noise, flying literally those samples. Stepped as rotorpy.simulate steps
    (controller on the state, then Multirotor.step), at --rate-hz.
Both errors are |p_true - p_setpoint| after each step from the flight's measure_from_s on, over
the same duration. Prints both RMS figures and their ratio, and writes
out/bench/flight_oracle.json. It is a benchmark: it never fails on the figures (a non-zero exit
means something could not run at all).

Frames: kinfly's world is z down (x forward, y right, gravity +z), its body FRD; RotorPy's world
is z up, its body FLU. The reference goes to RotorPy as (x, -y, -z), velocity, acceleration and
jerk alike, and yaw as -yaw: a rotation by 180 degrees about x, which maps FRD onto FLU as well
and leaves every error's length unchanged, so the two RMS figures compare directly.
"""
from __future__ import annotations

import argparse
import importlib.metadata
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from rotorpy.controllers.quadrotor_control import SE3Control
from rotorpy.vehicles.hummingbird_params import quad_params
from rotorpy.vehicles.multirotor import Multirotor

REPO_ROOT = Path(__file__).resolve().parents[2]
GRAVITY_M_S2 = 9.81  # RotorPy's and kinfly's
# kinfly world (z down) -> RotorPy world (z up): 180 degrees about x.
KINFLY_TO_ROTORPY = np.diag([1.0, -1.0, -1.0])
TAIL_S = 1.0  # the steady error is the mean over the last second, as kinfly-flight-bench's


def run_json(command: list[str]) -> dict[str, Any]:
    done = subprocess.run(command, check=True, capture_output=True, text=True)
    return json.loads(done.stdout)


def rotorpy_reference(dump: dict[str, Any]) -> list[dict[str, Any]]:
    """kinfly's sampled setpoints as RotorPy's flat outputs, in RotorPy's world."""
    samples = dump["samples"]
    to_r = KINFLY_TO_ROTORPY
    position = np.asarray(samples["p_world_m"]) @ to_r.T
    velocity = np.asarray(samples["v_world_m_s"]) @ to_r.T
    acceleration = np.asarray(samples["a_world_m_s2"]) @ to_r.T
    jerk = np.asarray(samples["j_world_m_s3"]) @ to_r.T
    return [{"x": position[k], "x_dot": velocity[k], "x_ddot": acceleration[k],
             "x_dddot": jerk[k], "x_ddddot": np.zeros(3),  # snap: SE3Control does not use it
             "yaw": -float(samples["yaw_rad"][k]), "yaw_dot": 0.0, "yaw_ddot": 0.0}
            for k in range(len(position))]


def fly_rotorpy(dump: dict[str, Any], rate_hz: int, aero: bool,
                gains: tuple[list[float], list[float]] | None = None) -> dict[str, Any]:
    """RotorPy's SE3Control on the true state of RotorPy's Hummingbird, round the reference; at
    its own position gains, or at gains = (K_p, K_v) per axis (kinfly's, which are the same in
    both frames: the axes only change sign)."""
    control_dt_s = float(dump["control_dt_s"])
    decimation = round(1.0 / (rate_hz * control_dt_s))
    if decimation < 1 or abs(decimation * rate_hz * control_dt_s - 1.0) > 1e-9:
        raise SystemExit(f"--rate-hz {rate_hz} does not divide the reference's "
                         f"{1.0 / control_dt_s:.0f} Hz")
    step_s = decimation * control_dt_s
    reference = rotorpy_reference(dump)[::decimation]
    times_s = np.asarray(dump["samples"]["t_s"])[::decimation]

    # At rest at the reference's first point, the rotors carrying the weight (as kinfly's plant
    # starts: FlightPlant::startHovering).
    hover_rad_s = np.sqrt(quad_params["mass"] * GRAVITY_M_S2 / (4 * quad_params["k_eta"]))
    state = {"x": reference[0]["x"].copy(), "v": np.zeros(3), "q": np.array([0.0, 0.0, 0.0, 1.0]),
             "w": np.zeros(3), "wind": np.zeros(3),
             "rotor_speeds": np.full(quad_params["num_rotors"], hover_rad_s)}
    vehicle = Multirotor(quad_params, initial_state=state, control_abstraction="cmd_motor_speeds",
                         aero=aero)
    controller = SE3Control(quad_params)
    if gains is not None:
        controller.kp_pos = np.asarray(gains[0], dtype=float)
        controller.kd_pos = np.asarray(gains[1], dtype=float)

    measure_from_s = float(dump["measure_from_s"])
    errors_m = []
    tail_errors = []
    tail_from_s = float(dump["duration_s"]) - TAIL_S
    start = time.process_time()
    for k in range(len(reference) - 1):
        control = controller.update(times_s[k], state, reference[k])
        state = vehicle.step(state, control, step_s)
        t_after_s = times_s[k + 1]
        if t_after_s < measure_from_s - 1e-9:
            continue
        error_m = state["x"] - reference[k + 1]["x"]
        errors_m.append(error_m)
        if t_after_s > tail_from_s + 1e-9:
            tail_errors.append(error_m)
    cpu_s = time.process_time() - start
    errors = np.asarray(errors_m)
    norms = np.linalg.norm(errors, axis=1)
    # The tail mean back in kinfly's world, so that it reads as kinfly-flight-bench's does.
    tail_mean_kinfly = KINFLY_TO_ROTORPY.T @ np.mean(np.asarray(tail_errors), axis=0)
    return {
        "rms_m": round(float(np.sqrt(np.mean(norms**2))), 5),
        "max_m": round(float(np.max(norms)), 5),
        "last_second_mean_error_m": round(float(np.linalg.norm(tail_mean_kinfly)), 5),
        "rate_hz": rate_hz,
        "aero": aero,
        "state": "true",
        "kp_pos_1_s2": controller.kp_pos.tolist(),
        "kd_pos_1_s": controller.kd_pos.tolist(),
        "kp_att": controller.kp_att,
        "kd_att": controller.kd_att,
        "cpu_s": round(cpu_s, 1),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--flight-bench", type=Path,
                        default=REPO_ROOT / "build" / "bin" / "kinfly-flight-bench")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "bench")
    parser.add_argument("--rate-hz", type=int, default=1000,
                        help="RotorPy's step and controller rate (kinfly's attitude loop: 1000; "
                             "rotorpy's examples: 100)")
    parser.add_argument("--no-aero", dest="aero", action="store_false",
                        help="without RotorPy's drag (rotor drag, induced inflow, parasitic drag; "
                             "kinfly's test plant has a linear drag of 0.15 N s/m instead)")
    args = parser.parse_args()

    bench = str(args.flight_bench)
    kinfly = run_json([bench])["position"]
    dump = run_json([bench, "--dump-figure-eight"])
    oracle = fly_rotorpy(dump, args.rate_hz, args.aero)
    # The same law at kinfly's gains (no integral: SE3Control has none) tells a difference of
    # gains from one of the law or the plant.
    at_kinfly_gains = fly_rotorpy(dump, args.rate_hz, args.aero,
                                  (kinfly["p_gain_1_s2"], kinfly["v_gain_1_s"]))
    kinfly_eight = kinfly["figure_eight"]
    report = {
        "figure_eight": {
            "size_m": kinfly["figure_eight_m"],
            "peak_speed_m_s": kinfly["figure_eight_peak_speed_m_s"],
            "trajectory_duration_s": dump["trajectory_duration_s"],
            "duration_s": dump["duration_s"],
            "measure_from_s": dump["measure_from_s"],
            "reference_samples": len(dump["samples"]["t_s"]),
        },
        "kinfly": {
            "rms_m": kinfly_eight["rms_m"],
            "max_m": kinfly_eight["max_m"],
            "last_second_mean_error_m": kinfly_eight["last_second_mean_error_m"],
            "state": "estimated (IMU, odometry poses)",
            "estimate_rms_m": kinfly_eight["estimate_rms_m"],
            "position_rate_hz": kinfly["rate_hz"],
            "attitude_rate_hz": kinfly["imu_hz"],
        },
        "rotorpy": {"version": importlib.metadata.version("rotorpy"),
                    "vehicle": "hummingbird", "controller": "SE3Control", **oracle},
        "rotorpy_at_kinfly_gains": {"controller": "SE3Control, kinfly's K_p and K_v",
                                    **at_kinfly_gains},
        "rms_ratio_kinfly_over_rotorpy": round(kinfly_eight["rms_m"] / oracle["rms_m"], 3),
        "frame": "reference to RotorPy as (x, -y, -z), yaw -yaw (kinfly z down, RotorPy z up)",
    }
    text = json.dumps(report, indent=2)
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "flight_oracle.json").write_text(text + "\n")
    print(f"figure eight position RMS: kinfly {1e3 * kinfly_eight['rms_m']:.1f} mm (on its "
          f"estimate) | RotorPy SE3Control {1e3 * oracle['rms_m']:.1f} mm (true state, "
          f"{args.rate_hz} Hz, aero {'on' if args.aero else 'off'}), "
          f"{1e3 * at_kinfly_gains['rms_m']:.1f} mm at kinfly's gains | kinfly/RotorPy "
          f"{report['rms_ratio_kinfly_over_rotorpy']:.2f}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
