#include "kinfly/flight/trajectory.h"

#include <Eigen/LU>
#include <algorithm>
#include <array>
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
// Speed and acceleration are sampled this often per segment to find the peaks the time
// allocation scales to; the peak of a degree-7 segment moves by well under 1 % between such
// samples.
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
      outOfRange("trajectory.max_accel_m_s2", max_accel_m_s2, 0.0, 20.0, Bound::kOpen),
      outOfRange("trajectory.max_jerk_m_s3", max_jerk_m_s3, 0.0, 200.0, Bound::kOpen),
      outOfRange("trajectory.max_yaw_rate_rad_s", max_yaw_rate_rad_s, 0.0, 10.0, Bound::kOpen));
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
  // and the constraints are unchanged in normalised time) at 1 / alpha the speed and 1 / alpha^2
  // the acceleration.
  double peak_m_s = 0.0, peak_m_s2 = 0.0, peak_m_s3 = 0.0;
  for (int i = 0; i < trajectory->segmentCount(); ++i) {
    const Segment& segment = trajectory->segments_[i];
    for (int j = 0; j <= kSpeedSamplesPerSegment; ++j) {
      const double t_s = segment.start_s + segment.duration_s * j / kSpeedSamplesPerSegment;
      const PositionSetpoint sp = trajectory->sample(t_s);
      peak_m_s = std::max(peak_m_s, sp.v_world_m_s.norm());
      peak_m_s2 = std::max(peak_m_s2, sp.a_world_m_s2.norm());
      peak_m_s3 = std::max(peak_m_s3, sp.j_world_m_s3.norm());
    }
  }
  if (peak_m_s == 0.0) return Trajectory::hold(waypoints_world_m.front(), yaw_rad);
  const double alpha = std::max({peak_m_s / params.max_speed_m_s,
                                 std::sqrt(peak_m_s2 / params.max_accel_m_s2),
                                 std::cbrt(peak_m_s3 / params.max_jerk_m_s3)});
  std::vector<Segment> scaled = trajectory->segments_;
  for (Segment& segment : scaled) segment.duration_s *= alpha;
  return Trajectory(std::move(scaled), waypoints_world_m.front(), waypoints_world_m.back(),
                    yaw_rad);
}

Trajectory Trajectory::hold(const Eigen::Vector3d& p_world_m, double yaw_rad) {
  return Trajectory({}, p_world_m, p_world_m, yaw_rad);
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
  const Segment& segment = segmentAt(t_s);
  const double s = (t_s - segment.start_s) / segment.duration_s;
  Eigen::Vector3d* const out[4] = {&sp.p_world_m, &sp.v_world_m_s, &sp.a_world_m_s2,
                                   &sp.j_world_m_s3};
  for (int k = 0; k < 4; ++k) {
    *out[k] = (derivativeRow(k, s, segment.duration_s, 1.0) * segment.coeffs).transpose();
  }
  return sp;
}

Eigen::Vector3d Trajectory::derivative(double t_s, int order) const {
  if (segments_.empty() || !(t_s < duration_s_) || t_s < 0.0 || order < 0 || order >= kN) {
    if (order != 0) return Eigen::Vector3d::Zero();
    return t_s < 0.0 ? first_world_m_ : last_world_m_;
  }
  const Segment& segment = segmentAt(t_s);
  const double s = (t_s - segment.start_s) / segment.duration_s;
  return (derivativeRow(order, s, segment.duration_s, 1.0) * segment.coeffs).transpose();
}

const Trajectory::Segment& Trajectory::segmentAt(double t_s) const {
  // The last segment starting at or before t_s.
  const auto after = std::upper_bound(
      segments_.begin(), segments_.end(), t_s,
      [](double t, const Segment& segment) { return t < segment.start_s; });
  return *(after - 1);
}

namespace {
// σ(s) = 35 s^4 - 84 s^5 + 70 s^6 - 20 s^7 and its first three derivatives, all but σ zero at
// s = 0 and σ - 1 with them at s = 1: rest at both ends. Its peak slope, at s = 1/2, is 35/16;
// its peak curvature, at s = (5 - √5) / 10, 7.5132 (where the third derivative is zero).
constexpr double kRestToRestPeakSpeed = 35.0 / 16.0;
constexpr double kRestToRestPeakAccel = 7.513188404399289;
constexpr double kRestToRestPeakJerk = 52.5;  // at s = 1/2

std::array<double, 4> restToRest(double s) {
  const double s2 = s * s, s3 = s2 * s, s4 = s3 * s;
  return {s4 * (35.0 - 84.0 * s + 70.0 * s2 - 20.0 * s3),
          s3 * (140.0 - 420.0 * s + 420.0 * s2 - 140.0 * s3),
          s2 * (420.0 - 1680.0 * s + 2100.0 * s2 - 840.0 * s3),
          s * (840.0 - 5040.0 * s + 8400.0 * s2 - 4200.0 * s3)};
}
}  // namespace

StraightLine::StraightLine(const Eigen::Vector3d& from_world_m, const Eigen::Vector3d& to_world_m,
                           const TrajectoryParams& params, double from_yaw_rad, double to_yaw_rad)
    : from_world_m_(from_world_m),
      delta_m_(to_world_m - from_world_m),
      from_yaw_rad_(from_yaw_rad),
      delta_yaw_rad_(std::remainder(to_yaw_rad - from_yaw_rad, 2.0 * M_PI)) {
  const double length_m = delta_m_.norm();
  duration_s_ = std::max({kRestToRestPeakSpeed * length_m / params.max_speed_m_s,
                          std::sqrt(kRestToRestPeakAccel * length_m / params.max_accel_m_s2),
                          std::cbrt(kRestToRestPeakJerk * length_m / params.max_jerk_m_s3),
                          kRestToRestPeakSpeed * std::abs(delta_yaw_rad_) /
                              params.max_yaw_rate_rad_s});
}

PositionSetpoint StraightLine::sample(double t_s) const {
  PositionSetpoint sp;
  if (!(t_s < duration_s_)) {  // after the end (a zero length too, and NaN): at rest there
    sp.p_world_m = from_world_m_ + delta_m_;
    sp.yaw_rad = from_yaw_rad_ + delta_yaw_rad_;
    return sp;
  }
  const double s = std::max(t_s, 0.0) / duration_s_;
  const std::array<double, 4> sigma = restToRest(s);
  const double T = duration_s_;
  sp.yaw_rad = from_yaw_rad_ + delta_yaw_rad_ * sigma[0];
  sp.p_world_m = from_world_m_ + delta_m_ * sigma[0];
  sp.v_world_m_s = delta_m_ * (sigma[1] / T);
  sp.a_world_m_s2 = delta_m_ * (sigma[2] / (T * T));
  sp.j_world_m_s3 = delta_m_ * (sigma[3] / (T * T * T));
  return sp;
}

Descent::Descent(const Eigen::Vector3d& from_world_m, double speed_m_s,
                 const TrajectoryParams& params, double yaw_rad)
    : from_world_m_(from_world_m),
      speed_m_s_(speed_m_s),
      accel_m_s2_(params.max_accel_m_s2),
      yaw_rad_(yaw_rad) {}

PositionSetpoint Descent::sample(double t_s) const {
  PositionSetpoint sp;
  sp.yaw_rad = yaw_rad_;
  sp.p_world_m = from_world_m_;
  const double t = std::isfinite(t_s) ? std::max(t_s, 0.0) : 0.0;
  const double ramp_s = speed_m_s_ / accel_m_s2_;
  if (t < ramp_s) {
    sp.p_world_m.z() += 0.5 * accel_m_s2_ * t * t;
    sp.v_world_m_s.z() = accel_m_s2_ * t;
    sp.a_world_m_s2.z() = accel_m_s2_;
  } else {
    sp.p_world_m.z() += 0.5 * speed_m_s_ * ramp_s + speed_m_s_ * (t - ramp_s);
    sp.v_world_m_s.z() = speed_m_s_;
  }
  return sp;
}

}  // namespace kinfly::flight
