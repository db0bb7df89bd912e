// Setpoints for the position loop over time: minimum-snap polynomial trajectories through
// waypoints (Mellinger and Kumar, ICRA 2011) for missions, and the simple ones the flight modes
// start inside the control tick: a straight line from rest to rest (take-off, go-to) and a
// descent that does not stop (land) (docs/flight.md, "Trajectories").
//
// A trajectory is built once, outside the control tick (it allocates and, for minimum snap,
// solves a linear system); sample() is const and allocates nothing. Every trajectory is a chain
// of polynomial segments per world axis, each in its own normalised time s = (t - t_i) / T_i in
// [0, 1], which keeps the solve well conditioned whatever the segment times. Before its start a
// trajectory holds its first point and after its end its last, at rest. A minimum-snap
// trajectory and a descent hold their yaw; a straight line turns it.
#pragma once

#include <Eigen/Core>
#include <vector>

#include "kinfly/core/status.h"
#include "kinfly/flight/position_controller.h"

namespace kinfly::flight {

struct TrajectoryParams {
  // [m/s] (0, 20] allocated segment times give this peak speed (times proportional to the
  // segment lengths, then all scaled together: a uniform time scale leaves the minimum-snap
  // shape unchanged, so one solve suffices) ...
  double max_speed_m_s = 1.0;
  // [m/s^2] (0, 20] ... or, where that is the tighter limit, this peak acceleration (scaling
  // the times by a scales it by 1 / a^2). PX4's MPC_ACC_HOR_MAX default; a descent reaches its
  // speed at this rate.
  double max_accel_m_s2 = 5.0;
  // [m/s^3] (0, 200] ... or this peak jerk: the tilt the attitude loop is asked to follow turns
  // at about jerk / g. Without it a hop of millimetres (a hold's setpoint to a mission's start)
  // took 0.1 s at the full acceleration, a 27 degree tilt demanded and taken back within 50 ms,
  // and the simulated drone tumbled 40 cm (docs/sim.md). 30 leaves the figure eights at 1 and
  // 2 m/s (peaks 8 and 29 m/s^3) as they were.
  double max_jerk_m_s3 = 30.0;
  // [rad/s] (0, 10] a straight line that turns the heading (a go-to given one) takes at least
  // the time that keeps its peak yaw rate within this: about 45°/s, PX4's MPC_YAWRAUTO_MAX
  // default. The odometry tracks a turn the IMU's prior carries, but the onboard map has to be
  // filled again where the camera now looks.
  double max_yaw_rate_rad_s = 0.785;
  Status validate() const;
};

class Trajectory {
 public:
  // Degree 7 (8 coefficients), the minimum-snap polynomial's: snap's Euler-Lagrange equation is
  // d^8 p / dt^8 = 0.
  static constexpr int kCoefficients = 8;

  // Through waypoints_world_m (at least 2, finite) in the given segment times (one per segment,
  // each > 0, finite), from rest to rest: per axis the piecewise polynomial that minimises the
  // integral of the squared snap with each waypoint met and velocity, acceleration, jerk and
  // snap continuous at every inner waypoint, as a quadratic programme with equality constraints
  // solved in closed form (its KKT system). The optimum is in fact continuous up to the sixth
  // derivative.
  static StatusOr<Trajectory> minimumSnapWithTimes(
      const std::vector<Eigen::Vector3d>& waypoints_world_m,
      const std::vector<double>& segment_times_s, double yaw_rad);
  // The same with the segment times allocated for params.max_speed_m_s.
  static StatusOr<Trajectory> minimumSnap(const std::vector<Eigen::Vector3d>& waypoints_world_m,
                                          const TrajectoryParams& params, double yaw_rad);
  static Trajectory hold(const Eigen::Vector3d& p_world_m, double yaw_rad);

  // Allocation-free. t_s from the trajectory's start.
  PositionSetpoint sample(double t_s) const;
  // [m/s^order] the order-th time derivative (0 to 7) at t_s; before the start and after the end
  // the position held there (order 0) and zero (at rest) as sample() gives.
  Eigen::Vector3d derivative(double t_s, int order) const;
  double durationS() const { return duration_s_; }
  int segmentCount() const { return static_cast<int>(segments_.size()); }
  // [s] from the start to the start of each segment.
  double segmentStartS(int i) const { return segments_[i].start_s; }

 private:
  // Column a holds axis a's coefficients c_k of s^k, s = (t - start_s) / duration_s.
  using Coefficients = Eigen::Matrix<double, kCoefficients, 3>;
  struct Segment {
    double start_s = 0.0;
    double duration_s = 0.0;
    Coefficients coeffs = Coefficients::Zero();
  };

  // The segment t_s falls in; t_s in [0, duration_s_).
  const Segment& segmentAt(double t_s) const;

  Trajectory(std::vector<Segment> segments, const Eigen::Vector3d& first_world_m,
             const Eigen::Vector3d& last_world_m, double yaw_rad);

  std::vector<Segment> segments_;
  Eigen::Vector3d first_world_m_;
  Eigen::Vector3d last_world_m_;
  double duration_s_ = 0.0;
  double yaw_rad_ = 0.0;
};

// From rest at one point to rest at another along the straight line between them, in closed
// form: the two-point minimum-snap polynomial p(s) = p0 + (p1 - p0) σ(s) with
// σ(s) = 35 s^4 - 84 s^5 + 70 s^6 - 20 s^7, s = t / T, T the shortest time that keeps the peak
// speed (35/16 |p1 - p0| / T), acceleration (7.513 |p1 - p0| / T^2) and jerk
// (52.5 |p1 - p0| / T^3) within the params. The heading turns the shorter way round from one yaw
// to the other along the same σ(s), T also long enough for its peak rate
// (35/16 |Δyaw| / T) to stay within max_yaw_rate_rad_s: a turn in place is a line of length 0.
// Made and sampled without allocating or solving: the flight modes start one inside the control
// tick (take-off, go-to, the way to a mission's start).
class StraightLine {
 public:
  StraightLine() = default;  // at rest at the origin
  // from, to and the yaws finite, params valid: the caller checks them once (FlightStack's
  // params, the modes' targets).
  StraightLine(const Eigen::Vector3d& from_world_m, const Eigen::Vector3d& to_world_m,
               const TrajectoryParams& params, double from_yaw_rad, double to_yaw_rad);
  PositionSetpoint sample(double t_s) const;
  double durationS() const { return duration_s_; }

 private:
  Eigen::Vector3d from_world_m_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d delta_m_ = Eigen::Vector3d::Zero();
  double duration_s_ = 0.0;
  double from_yaw_rad_ = 0.0;
  double delta_yaw_rad_ = 0.0;  // in [-pi, pi]: the shorter way round
};

// Straight down from a point (world z grows), speeding up at params.max_accel_m_s2 to the
// descent speed and then on at that speed without end: the landed detector, not the
// trajectory, ends a landing. The drone meets the ground at the set speed and the loop pushes
// on into it until the thrust falls under the landed ratio, as PX4's land mode does; a descent
// that stopped at the ground height it believed in would hover above a floor that is lower.
// Allocation-free like StraightLine.
class Descent {
 public:
  Descent() = default;
  Descent(const Eigen::Vector3d& from_world_m, double speed_m_s, const TrajectoryParams& params,
          double yaw_rad);
  PositionSetpoint sample(double t_s) const;

 private:
  Eigen::Vector3d from_world_m_ = Eigen::Vector3d::Zero();
  double speed_m_s_ = 0.0;
  double accel_m_s2_ = 1.0;
  double yaw_rad_ = 0.0;
};

}  // namespace kinfly::flight
