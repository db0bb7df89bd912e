// Standard normal vectors from a fixed seed, for the flight tests' sensor noise: one generator
// type, so that the plant's IMU and the odometry's poses draw alike.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <random>

namespace kinfly::flight::test {

// Drawn x, y, z in that order (a constructor's arguments have no order of evaluation).
class Gaussian {
 public:
  explicit Gaussian(uint32_t seed) : rng_(seed) {}
  Eigen::Vector3d operator()() {
    Eigen::Vector3d v;
    for (int i = 0; i < 3; ++i) v[i] = normal_(rng_);
    return v;
  }

 private:
  std::mt19937 rng_;
  std::normal_distribution<double> normal_{0.0, 1.0};
};

}  // namespace kinfly::flight::test
