// The flight stack's inner loops closed around the test plant (flight_plant.h), and the step
// response figures, for the closed-loop tests (test_flight_loop.cpp) and kinfly-flight-bench:
// one definition of a step and its rise and settling, so the test and the benchmark measure
// the same thing.
#pragma once

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <vector>

#include "flight_plant.h"
#include "kinfly/flight/attitude_controller.h"
#include "kinfly/flight/mixer.h"
#include "kinfly/flight/rate_controller.h"

namespace kinfly::flight::test {

constexpr double kControlDtS = 0.001;            // [s] the 1 kHz control tick
constexpr double kGyroNoiseDensity = 5e-5;       // [rad/s/sqrt(Hz)] an ICM-42688-class gyro
constexpr double kRateStepRadS = 1.0;            // [rad/s] the body-rate step, about x_body
constexpr double kAttitudeStepRad = 10.0 * M_PI / 180.0;  // the attitude step, about x_body
constexpr double kStepDurationS = 1.0;           // [s] long enough for the integrators to settle

// A response y(t) sampled every kControlDtS from the step at t = 0, towards target from 0.
struct StepResponse {
  std::vector<double> y;
  double target = 0.0;
};

struct StepFigures {
  double rise_time_s = NAN;      // 10 % to 90 % of the target
  double overshoot = NAN;        // [-] beyond the target, as a fraction of it; 0 if never above
  double settling_time_s = NAN;  // from the step to staying within 2 % of the target
  double final_error = NAN;      // [-] mean over the last 0.1 s, as a fraction of the target
};

inline StepFigures stepFigures(const StepResponse& response) {
  const std::vector<double>& y = response.y;
  const double target = response.target;
  // The time y first reaches a fraction of the target, between samples by linear interpolation.
  auto crossing_s = [&](double fraction) {
    for (size_t k = 1; k < y.size(); ++k) {
      if (y[k] / target >= fraction) {
        const double a = y[k - 1] / target;
        const double b = y[k] / target;
        return kControlDtS * (static_cast<double>(k - 1) + (fraction - a) / (b - a));
      }
    }
    return static_cast<double>(NAN);
  };
  StepFigures figures;
  figures.rise_time_s = crossing_s(0.9) - crossing_s(0.1);
  figures.overshoot = std::max(0.0, *std::max_element(y.begin(), y.end()) / target - 1.0);
  size_t last_outside = 0;
  for (size_t k = 0; k < y.size(); ++k) {
    if (std::abs(y[k] / target - 1.0) > 0.02) last_outside = k + 1;
  }
  figures.settling_time_s = kControlDtS * static_cast<double>(last_outside);
  const size_t tail = static_cast<size_t>(0.1 / kControlDtS);
  double sum = 0.0;
  for (size_t k = y.size() - tail; k < y.size(); ++k) sum += y[k];
  figures.final_error = sum / static_cast<double>(tail) / target - 1.0;
  return figures;
}

// [rad] roll of q_world_body about world x, exact for a pure roll.
inline double rollRad(const Eigen::Quaterniond& q_world_body) {
  const Eigen::Matrix3d R_world_body = q_world_body.toRotationMatrix();
  return std::atan2(R_world_body(2, 1), R_world_body(2, 2));
}

// From hover, a step of kRateStepRadS in the roll-rate setpoint through the rate PID.
inline StepResponse flyRateStep(const Vehicle& vehicle, const RateController::Params& params,
                                double gyro_noise_density, uint32_t seed) {
  FlightPlant plant(vehicle, gyro_noise_density, seed);
  plant.startHovering();
  RateController rate(params, vehicle);
  const Mixer mixer(vehicle);
  MixerSaturation saturation;
  RateSetpoint setpoint;
  setpoint.omega_body_rad_s.x() = kRateStepRadS;
  StepResponse response{{}, kRateStepRadS};
  const int ticks = static_cast<int>(kStepDurationS / kControlDtS);
  response.y.reserve(ticks);
  for (int k = 0; k < ticks; ++k) {
    const Eigen::Vector3d moment_body_nm =
        rate.update(setpoint, plant.gyroBodyRadS(), kControlDtS, saturation);
    const MixerOutput out = mixer.mix({vehicle.weightN(), moment_body_nm});
    saturation = out.saturation;
    plant.step(out.rotor_speed_rad_s, kControlDtS);
    response.y.push_back(plant.state().omega_body_rad_s.x());
  }
  return response;
}

// From level hover, the attitude q_world_body every tick after the setpoint jumps to
// q_world_body_sp, with the given controller.
inline std::vector<Eigen::Quaterniond> flyAttitude(const Vehicle& vehicle,
                                                   AttitudeController controller,
                                                   const Eigen::Quaterniond& q_world_body_sp,
                                                   double gyro_noise_density, uint32_t seed) {
  FlightPlant plant(vehicle, gyro_noise_density, seed);
  plant.startHovering();
  const Mixer mixer(vehicle);
  MixerSaturation saturation;
  const int ticks = static_cast<int>(kStepDurationS / kControlDtS);
  std::vector<Eigen::Quaterniond> q_world_body;
  q_world_body.reserve(ticks);
  for (int k = 0; k < ticks; ++k) {
    const Eigen::Vector3d moment_body_nm =
        controller.update(plant.state().q_world_body, q_world_body_sp, plant.gyroBodyRadS(),
                          kControlDtS, saturation);
    // Tilted, the rotors lift the weight only with the collective thrust grown by 1/cos.
    const double thrust_n =
        vehicle.weightN() / (plant.state().q_world_body * Eigen::Vector3d::UnitZ()).z();
    const MixerOutput out = mixer.mix({thrust_n, moment_body_nm});
    saturation = out.saturation;
    plant.step(out.rotor_speed_rad_s, kControlDtS);
    q_world_body.push_back(plant.state().q_world_body);
  }
  return q_world_body;
}

// The roll response to a step of kAttitudeStepRad about x from level hover.
inline StepResponse flyAttitudeStep(const Vehicle& vehicle, const AttitudeController& controller,
                                    double gyro_noise_density, uint32_t seed) {
  const Eigen::Quaterniond q_world_body_sp(
      Eigen::AngleAxisd(kAttitudeStepRad, Eigen::Vector3d::UnitX()));
  StepResponse response{{}, kAttitudeStepRad};
  for (const Eigen::Quaterniond& q_world_body :
       flyAttitude(vehicle, controller, q_world_body_sp, gyro_noise_density, seed)) {
    response.y.push_back(rollRad(q_world_body));
  }
  return response;
}

}  // namespace kinfly::flight::test
