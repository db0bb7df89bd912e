#include "kinfly/sim/barometer.h"

#include <cmath>

#include "kinfly/core/range_check.h"

namespace kinfly::sim {

Status BarometerParams::validate() const {
  return firstError(outOfRange("baro.rate_hz", rate_hz, 0.0, 1000.0),
                    outOfRange("baro.noise_m", noise_m, 0.0, 10.0),
                    outOfRange("baro.drift_m_rt_s", drift_m_rt_s, 0.0, 1.0),
                    outOfRange("baro.site_altitude_m", site_altitude_m, -500.0, 9000.0));
}

Barometer::Barometer(const BarometerParams& params) : params_(params), random_(params.seed) {}

double Barometer::read(double height_m) {
  const double reading =
      params_.site_altitude_m + height_m + drift_m_ + params_.noise_m * random_();
  if (params_.rate_hz > 0.0) drift_m_ += params_.drift_m_rt_s / std::sqrt(params_.rate_hz) * random_();
  return reading;
}

}  // namespace kinfly::sim
