// The simulator's one source of randomness: normal deviates whose sequence is fixed by the seed
// alone, on any standard library. mt19937_64's output is fixed by the C++ standard, but
// std::normal_distribution's algorithm is each library's own choice, so the deviates are drawn
// here (Box-Muller) and a flight gives the same figures for its seed wherever it runs.
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <cstdint>
#include <random>

namespace kinfly::sim {

class NormalRandom {
 public:
  explicit NormalRandom(uint64_t seed) : engine_(seed) {}

  // Uniform in [0, 1), from the top 53 bits of one draw.
  double uniform() { return static_cast<double>(engine_() >> 11) * 0x1.0p-53; }

  // Standard normal.
  double operator()() {
    if (has_spare_) {
      has_spare_ = false;
      return spare_;
    }
    const double radius = std::sqrt(-2.0 * std::log(1.0 - uniform()));  // 1 - u is in (0, 1]
    const double angle = 2.0 * M_PI * uniform();
    spare_ = radius * std::sin(angle);
    has_spare_ = true;
    return radius * std::cos(angle);
  }

  // Three standard normals drawn x, y, z in that order (a constructor's arguments have none).
  Eigen::Vector3d vector3() {
    Eigen::Vector3d v;
    for (int i = 0; i < 3; ++i) v[i] = (*this)();
    return v;
  }

 private:
  std::mt19937_64 engine_;
  double spare_ = 0.0;
  bool has_spare_ = false;
};

}  // namespace kinfly::sim
