#include "kinfly/flight/trajectory.h"

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <string>
#include <utility>

#include "kinfly/core/range_check.h"

namespace kinfly::flight {

namespace {

constexpr int kN = Trajectory::kCoefficients;
constexpr int kSnap = 4;  // the derivative whose square is minimised
// Velocity, acceleration and jerk are zero at both ends: rest to rest.
constexpr int kEndDerivatives = 3;
// Speed is sampled this often per segment to find the peak the time allocation scales to; the
// peak of a degree-7 segment moves by well under 1 % between such samples.
constexpr int kSpeedSamplesPerSegment = 64;
// [m] A segment between two (nearly) equal waypoints still gets time, as if it were this long.
constexpr double kMinAllocatedLengthM = 0.05;

// d^k/ds^k of s^i: i! / (i - k)! s^(i - k).
double powerDerivative(int i, int k, double s) {
  if (i < k) return 0.0;
  double factor = 1.0;
  for (int j = 0; j < k; ++j) factor *= i - j;
  return factor * std::pow(s, i - k);
}

// The k-th time derivative of a segment as a row over its coefficients, at normalised time s,
// times time_scale_s^k (a common scale keeps the rows of different orders comparable).
Eigen::Matrix<double, 1, kN> derivativeRow(int k, double s, double duration_s,
                                           double time_scale_s) {
  Eigen::Matrix<double, 1, kN> row;
  const double scale = std::pow(time_scale_s / duration_s, k);
  for (int i = 0; i < kN; ++i) row(i) = scale * powerDerivative(i, k, s);
  return row;
}

bool finite(const Eigen::Vector3d& v) { return v.allFinite(); }

Status checkWaypoints(const std::vector<Eigen::Vector3d>& waypoints_world_m) {
  if (waypoints_world_m.size() < 2) {
    return Status::error("trajectory: needs at least 2 waypoints (got " +
                         std::to_string(waypoints_world_m.size()) + ")");
  }
  for (size_t i = 0; i < waypoints_world_m.size(); ++i) {
    if (!finite(waypoints_world_m[i])) {
      return Status::error("trajectory: waypoint " + std::to_string(i) + " is not finite");
    }
  }
  return {};
}

}  // namespace

Status TrajectoryParams::validate() const {
  return firstError(
      outOfRange("trajectory.max_speed_m_s", max_speed_m_s, 0.0, 20.0, Bound::kOpen),
      outOfRange("trajectory.land_speed_m_s", land_speed_m_s, 0.0, 5.0, Bound::kOpen),
      outOfRange("trajectory.land_accel_m_s2", land_accel_m_s2, 0.0, 10.0, Bound::kOpen));
}

Trajectory::Trajectory(std::vector<Segment> segments, const Eigen::Vector3d& first_world_m,
                       const Eigen::Vector3d& last_world_m, double yaw_rad)
    : segments_(std::move(segments)),
      first_world_m_(first_world_m),
      last_world_m_(last_world_m),
      yaw_rad_(yaw_rad) {
  double start_s = 0.0;
  for (Segment& segment : segments_) {
    segment.start_s = start_s;
    start_s += segment.duration_s;
  }
  duration_s_ = start_s;
}

StatusOr<Trajectory> Trajectory::minimumSnapWithTimes(
    const std::vector<Eigen::Vector3d>& waypoints_world_m,
    const std::vector<double>& segment_times_s, double yaw_rad) {
  if (Status valid = checkWaypoints(waypoints_world_m); !valid.ok()) return valid;
  const int segments = static_cast<int>(waypoints_world_m.size()) - 1;
  if (static_cast<int>(segment_times_s.size()) != segments) {
    return Status::error("trajectory: " + std::to_string(segment_times_s.size()) +
                         " segment times for " + std::to_string(segments) + " segments");
  }
  for (int i = 0; i < segments; ++i) {
    if (Status valid = outOfRange("trajectory: segment_times_s[" + std::to_string(i) + "]",
                                  segment_times_s[i], 0.0, 1e6, Bound::kOpen);
        !valid.ok()) {
      return valid;
    }
  }
  if (!std::isfinite(yaw_rad)) return Status::error("trajectory: yaw_rad is not finite");

  // min c' H c subject to A c = b, per axis (the same H and A for all three: one solve with
  // three right-hand sides). c stacks the segments' coefficients.
  const int unknowns = kN * segments;
  const int constraints = 2 * segments + 2 * kEndDerivatives + kSnap * (segments - 1);
  double time_scale_s = 0.0;
  for (double t : segment_times_s) time_scale_s += t / segments;

  Eigen::MatrixXd kkt = Eigen::MatrixXd::Zero(unknowns + constraints, unknowns + constraints);
  Eigen::MatrixXd rhs = Eigen::MatrixXd::Zero(unknowns + constraints, 3);
  // H: integral over [0, T] of (d^4 p / dt^4)^2 = T^-7 integral over [0, 1] of (d^4 p / ds^4)^2,
  // each term of which integrates in closed form; scaled by time_scale_s^7 like the rows below.
  for (int seg = 0; seg < segments; ++seg) {
    const double scale = std::pow(time_scale_s / segment_times_s[seg], 2 * kSnap - 1);
    for (int i = kSnap; i < kN; ++i) {
      for (int j = kSnap; j < kN; ++j) {
        kkt(kN * seg + i, kN * seg + j) = 2.0 * scale * powerDerivative(i, kSnap, 1.0) *
                                          powerDerivative(j, kSnap, 1.0) /
                                          (i + j - 2 * kSnap + 1);
      }
    }
  }
  int row = unknowns;
  auto constrain = [&](int seg, int k, double s, double sign) {
    kkt.block<1, kN>(row, kN * seg) +=
        sign * derivativeRow(k, s, segment_times_s[seg], time_scale_s);
  };
  for (int seg = 0; seg < segments; ++seg) {  // each segment starts and ends at its waypoints
    constrain(seg, 0, 0.0, 1.0);
    rhs.row(row++) = waypoints_world_m[seg].transpose();
    constrain(seg, 0, 1.0, 1.0);
    rhs.row(row++) = waypoints_world_m[seg + 1].transpose();
  }
  for (int k = 1; k <= kEndDerivatives; ++k) {  // at rest at both ends (rhs stays 0)
    constrain(0, k, 0.0, 1.0);
    ++row;
    constrain(segments - 1, k, 1.0, 1.0);
    ++row;
  }
  for (int seg = 0; seg + 1 < segments; ++seg) {  // continuous up to snap at inner waypoints
    for (int k = 1; k <= kSnap; ++k) {
      constrain(seg, k, 1.0, 1.0);
      constrain(seg + 1, k, 0.0, -1.0);
      ++row;
    }
  }
  kkt.topRightCorner(unknowns, constraints) =
      kkt.bottomLeftCorner(constraints, unknowns).transpose();
  // Nonsingular: the constraints are independent and H is positive definite on their null space
  // (a zero-snap, at-rest, zero-valued spline is zero), but the system is indefinite: full
  // pivoting.
  const Eigen::FullPivLU<Eigen::MatrixXd> lu(kkt);
  const Eigen::MatrixXd solution = lu.solve(rhs);
  if (!lu.isInvertible() || !solution.allFinite()) {
    return Status::error("trajectory: the minimum-snap system could not be solved");
  }

  std::vector<Segment> out(segments);
  for (int seg = 0; seg < segments; ++seg) {
    out[seg].duration_s = segment_times_s[seg];
    out[seg].coeffs = solution.block<kN, 3>(kN * seg, 0);
  }
  return Trajectory(std::move(out), waypoints_world_m.front(), waypoints_world_m.back(), yaw_rad);
}

StatusOr<Trajectory> Trajectory::minimumSnap(const std::vector<Eigen::Vector3d>& waypoints_world_m,
                                             const TrajectoryParams& params, double yaw_rad) {
  if (Status valid = params.validate(); !valid.ok()) return valid;
  if (Status valid = checkWaypoints(waypoints_world_m); !valid.ok()) return valid;
  std::vector<double> times_s;
  for (size_t i = 0; i + 1 < waypoints_world_m.size(); ++i) {
    const double length_m = (waypoints_world_m[i + 1] - waypoints_world_m[i]).norm();
    times_s.push_back(std::max(length_m, kMinAllocatedLengthM) / params.max_speed_m_s);
  }
  auto trajectory = minimumSnapWithTimes(waypoints_world_m, times_s, yaw_rad);
  if (!trajectory.ok()) return trajectory;
  // Scaling every time by alpha gives p(t / alpha), the same shape (the cost scales as a whole
  // and the constraints are unchanged in normalised time) at 1 / alpha the speed.
  double peak_m_s = 0.0;
  for (int i = 0; i < trajectory->segmentCount(); ++i) {
    const Segment& segment = trajectory->segments_[i];
    for (int j = 0; j <= kSpeedSamplesPerSegment; ++j) {
      const double t_s = segment.start_s + segment.duration_s * j / kSpeedSamplesPerSegment;
      peak_m_s = std::max(peak_m_s, trajectory->sample(t_s).v_world_m_s.norm());
    }
  }
  if (peak_m_s == 0.0) return Trajectory::hold(waypoints_world_m.front(), yaw_rad);
  std::vector<Segment> scaled = trajectory->segments_;
  for (Segment& segment : scaled) segment.duration_s *= peak_m_s / params.max_speed_m_s;
  return Trajectory(std::move(scaled), waypoints_world_m.front(), waypoints_world_m.back(),
                    yaw_rad);
}

Trajectory Trajectory::hold(const Eigen::Vector3d& p_world_m, double yaw_rad) {
  return Trajectory({}, p_world_m, p_world_m, yaw_rad);
}

StatusOr<Trajectory> Trajectory::goTo(const Eigen::Vector3d& p_from_world_m,
                                      const Eigen::Vector3d& p_to_world_m,
                                      const TrajectoryParams& params, double yaw_rad) {
  if (Status valid = params.validate(); !valid.ok()) return valid;
  // Zero length: no time to allocate, nothing to fly.
  if (finite(p_from_world_m) && p_from_world_m == p_to_world_m) return hold(p_to_world_m, yaw_rad);
  return minimumSnap({p_from_world_m, p_to_world_m}, params, yaw_rad);
}

StatusOr<Trajectory> Trajectory::land(const Eigen::Vector3d& p_from_world_m, double ground_z_m,
                                      const TrajectoryParams& params, double yaw_rad) {
  if (Status valid = params.validate(); !valid.ok()) return valid;
  if (!finite(p_from_world_m)) return Status::error("trajectory: land's start is not finite");
  if (!std::isfinite(yaw_rad)) return Status::error("trajectory: yaw_rad is not finite");
  if (!std::isfinite(ground_z_m) || !(ground_z_m > p_from_world_m.z())) {
    return Status::error("trajectory: land's ground_z_m must be below the start (z down: above " +
                         std::to_string(p_from_world_m.z()) + ", got " +
                         std::to_string(ground_z_m) + ")");
  }
  const double drop_m = ground_z_m - p_from_world_m.z();
  const double a = params.land_accel_m_s2;
  // Too short a drop to reach the speed: speed up to halfway and slow down again.
  const double speed_m_s = std::min(params.land_speed_m_s, std::sqrt(a * drop_m));
  const double ramp_s = speed_m_s / a;
  const double ramp_m = 0.5 * a * ramp_s * ramp_s;
  const double cruise_s = (drop_m - 2.0 * ramp_m) / speed_m_s;

  // z(s) over each piece in its normalised time s: speeding up, cruising, slowing down.
  auto piece = [&](double duration_s, double z0_m, double v0_m_s, double accel_m_s2) {
    Segment segment;
    segment.duration_s = duration_s;
    segment.coeffs.row(0) = p_from_world_m.transpose();
    segment.coeffs(0, 2) = z0_m;
    segment.coeffs(1, 2) = v0_m_s * duration_s;
    segment.coeffs(2, 2) = 0.5 * accel_m_s2 * duration_s * duration_s;
    return segment;
  };
  std::vector<Segment> segments;
  segments.push_back(piece(ramp_s, p_from_world_m.z(), 0.0, a));
  if (cruise_s > 0.0) {
    segments.push_back(piece(cruise_s, p_from_world_m.z() + ramp_m, speed_m_s, 0.0));
  }
  segments.push_back(piece(ramp_s, ground_z_m - ramp_m, speed_m_s, -a));
  Eigen::Vector3d ground_world_m = p_from_world_m;
  ground_world_m.z() = ground_z_m;
  return Trajectory(std::move(segments), p_from_world_m, ground_world_m, yaw_rad);
}

PositionSetpoint Trajectory::sample(double t_s) const {
  PositionSetpoint sp;
  sp.yaw_rad = yaw_rad_;
  if (segments_.empty() || !(t_s < duration_s_)) {  // after the end (and NaN): at rest there
    sp.p_world_m = last_world_m_;
    return sp;
  }
  if (t_s < 0.0) {
    sp.p_world_m = first_world_m_;
    return sp;
  }
  // The last segment starting at or before t_s.
  const auto after = std::upper_bound(
      segments_.begin(), segments_.end(), t_s,
      [](double t, const Segment& segment) { return t < segment.start_s; });
  const Segment& segment = *(after - 1);
  const double s = (t_s - segment.start_s) / segment.duration_s;
  Eigen::Vector3d* const out[4] = {&sp.p_world_m, &sp.v_world_m_s, &sp.a_world_m_s2,
                                   &sp.j_world_m_s3};
  for (int k = 0; k < 4; ++k) {
    *out[k] = (derivativeRow(k, s, segment.duration_s, 1.0) * segment.coeffs).transpose();
  }
  return sp;
}

}  // namespace kinfly::flight
