// Setpoints for the position loop over time: minimum-snap polynomial trajectories through
// waypoints (Mellinger and Kumar, ICRA 2011), and the simple ones a flight mode needs: hold a
// point, go to a point (a rest-to-rest minimum-snap), land (descend at a set speed to the
// ground) (docs/flight.md, "Trajectories").
//
// A trajectory is built once, outside the control tick (it allocates and, for minimum snap,
// solves a linear system); sample() is const and allocates nothing. Every trajectory is a chain
// of polynomial segments per world axis, each in its own normalised time s = (t - t_i) / T_i in
// [0, 1], which keeps the solve well conditioned whatever the segment times. Before its start a
// trajectory holds its first point and after its end its last, at rest. Yaw is held constant.
#pragma once

#include <Eigen/Core>
#include <vector>

#include "kinfly/core/status.h"
#include "kinfly/flight/position_controller.h"

namespace kinfly::flight {

struct TrajectoryParams {
  // [m/s] (0, 20] allocated segment times give this peak speed (times proportional to the
  // segment lengths, then all scaled together: a uniform time scale leaves the minimum-snap
  // shape unchanged, so one solve suffices).
  double max_speed_m_s = 1.0;
  double land_speed_m_s = 0.5;   // [m/s] (0, 5] descent speed when landing
  double land_accel_m_s2 = 1.0;  // [m/s^2] (0, 10] to reach it and to stop at the ground
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
  // Rest to rest from p_from to p_to, its time allocated for params.max_speed_m_s; a hold when
  // the two are the same point.
  static StatusOr<Trajectory> goTo(const Eigen::Vector3d& p_from_world_m,
                                   const Eigen::Vector3d& p_to_world_m,
                                   const TrajectoryParams& params, double yaw_rad);
  // Straight down (world z grows) from p_from to the height ground_z_m: speeds up at
  // land_accel_m_s2 to land_speed_m_s, descends, and slows down at the same rate to stop on the
  // ground (a triangle profile when the drop is too short to reach the speed).
  static StatusOr<Trajectory> land(const Eigen::Vector3d& p_from_world_m, double ground_z_m,
                                   const TrajectoryParams& params, double yaw_rad);

  // Allocation-free. t_s from the trajectory's start.
  PositionSetpoint sample(double t_s) const;
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

  Trajectory(std::vector<Segment> segments, const Eigen::Vector3d& first_world_m,
             const Eigen::Vector3d& last_world_m, double yaw_rad);

  std::vector<Segment> segments_;
  Eigen::Vector3d first_world_m_;
  Eigen::Vector3d last_world_m_;
  double duration_s_ = 0.0;
  double yaw_rad_ = 0.0;
};

}  // namespace kinfly::flight
