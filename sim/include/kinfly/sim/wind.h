// The air the drone flies through: a mean wind, Dryden turbulence (MIL-F-8785C, low altitude)
// and scripted gusts and steps (docs/sim.md, "Wind").
//
// Turbulence, per axis of the mean wind's frame (u along it, v across, w vertical), is white
// noise of two-sided spectral density pi through MIL-F-8785C's forming filters
//   H_u(s) = sigma_u sqrt(2 L_u / (pi V)) / (1 + (L_u/V) s)
//   H_v(s) = sigma_v sqrt(L_v / (pi V)) (1 + sqrt(3) (L_v/V) s) / (1 + (L_v/V) s)^2   (w alike)
// so each component has variance sigma^2. Low-altitude scale lengths and intensities, h in feet:
//   L_w = h, L_u = L_v = h / (0.177 + 0.000823 h)^1.2,
//   sigma_w = 0.1 W20, sigma_u / sigma_w = sigma_v / sigma_w = 1 / (0.177 + 0.000823 h)^0.4,
// W20 the wind speed at 20 ft. The model holds for 10 ft <= h <= 1000 ft; an indoor or
// near-ground drone is below that, so h is clamped to 10 ft (the scale lengths then stay a few
// metres, not the room's centimetres). V is the air speed past the drone, at least
// min_airspeed_m_s: Taylor's frozen turbulence does not hold for a body at rest in still air.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "kinfly/core/status.h"
#include "kinfly/sim/random.h"

namespace kinfly::sim {

struct WindParams {
  // [m/s] the mean wind in the world (z down), |w| <= 30
  Eigen::Vector3d mean_world_m_s = Eigen::Vector3d::Zero();
  // [m/s] [0, 30] W20, the wind at 20 ft that sets the turbulence intensities (0: none)
  double turbulence_w20_m_s = 0.0;
  double min_airspeed_m_s = 1.0;  // [m/s] (0, 30] the least V in the forming filters
  uint64_t seed = 1;
  Status validate() const;
};

// A 1 - cos gust (MIL-F-8785C's discrete gust): from start_s, the air's velocity grows by
// amplitude (1 - cos(pi t / duration)) / 2 up to amplitude at duration, and back to 0 at twice it.
struct Gust {
  double start_s = 0.0;                                         // [s] simulation time
  double duration_s = 1.0;                                      // [s] > 0 the rise, and the fall
  Eigen::Vector3d amplitude_world_m_s = Eigen::Vector3d::Zero();  // [m/s] at its peak
};

class Wind {
 public:
  explicit Wind(const WindParams& params);

  // From time_s on, the mean wind is mean_world_m_s (a wind step).
  void setMean(const Eigen::Vector3d& mean_world_m_s) { params_.mean_world_m_s = mean_world_m_s; }
  void addGust(const Gust& gust) { gusts_.push_back(gust); }

  // The air's velocity at the drone after a step of dt_s ending at time_s: the mean, the
  // turbulence (its filters stepped by dt_s at the drone's height and air speed) and the gusts.
  Eigen::Vector3d step(double time_s, double dt_s, double height_m,
                       const Eigen::Vector3d& v_world_m_s);

  // The turbulence's standard deviations (u, v, w) and scale lengths [m] at a height, for tests
  // and docs.
  Eigen::Vector3d sigmaMS(double height_m) const;
  Eigen::Vector3d scaleLengthM(double height_m) const;
  const Eigen::Vector3d& turbulenceMeanFrameMS() const { return turbulence_uvw_m_s_; }

 private:
  WindParams params_;
  NormalRandom random_;
  std::vector<Gust> gusts_;
  double u_state_ = 0.0;           // the u filter's output
  Eigen::Vector2d v_state_ = Eigen::Vector2d::Zero();  // (x, dx/dt) of v's second-order filter
  Eigen::Vector2d w_state_ = Eigen::Vector2d::Zero();
  Eigen::Vector3d turbulence_uvw_m_s_ = Eigen::Vector3d::Zero();
};

}  // namespace kinfly::sim
