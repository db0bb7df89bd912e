// The simulated barometer (docs/sim.md, "Barometer"): a pressure altitude, up, from the site's
// altitude, read at its own rate. Each reading is the true height plus a drift that walks
// randomly (the weather, the building's air) and white noise.
//
// The noise is the MS5611-01BA03's resolution at its finest oversampling (OSR 4096: 0.012 mbar
// RMS, its datasheet), about 0.10 m near sea level; 50 readings a second is what a flight
// controller reads it at with time to spare. The drift's walk is kinfly's choice: about 8 cm in a
// minute, a pressure change of 1 Pa a minute.
#pragma once

#include <cstdint>

#include "kinfly/core/status.h"
#include "kinfly/sim/random.h"

namespace kinfly::sim {

struct BarometerParams {
  double rate_hz = 50.0;           // [Hz] [0, 1000]; 0: no barometer
  double noise_m = 0.10;           // [m] [0, 10] 1σ per reading
  double drift_m_rt_s = 0.01;      // [m/sqrt(s)] [0, 1]
  double site_altitude_m = 100.0;  // [m] [-500, 9000] the pressure altitude at height 0
  uint64_t seed = 4;
  Status validate() const;
};

class Barometer {
 public:
  explicit Barometer(const BarometerParams& params);

  // The reading at height_m (up, from the world's origin); the drift walks by one period.
  double read(double height_m);

  double driftM() const { return drift_m_; }
  const BarometerParams& params() const { return params_; }

 private:
  BarometerParams params_;
  NormalRandom random_;
  double drift_m_ = 0.0;
};

}  // namespace kinfly::sim
