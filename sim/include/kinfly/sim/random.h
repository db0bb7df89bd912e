// The simulator's one source of randomness: normal deviates whose sequence is fixed by the seed
// alone, on any standard library. mt19937_64's output is fixed by the C++ standard, but
// std::normal_distribution's algorithm is each library's own choice; Boost.Random's is in its
// headers (a ziggurat after Marsaglia and Tsang), so a flight gives the same figures for its seed
// wherever the same Boost builds it (Debian 12's 1.74; the test pins the first deviates). The
// ziggurat takes a table lookup and a multiply for most deviates: the depth camera draws one a
// return, up to 9.2 M a second at VGA, where Box-Muller's logarithm, sine and cosine cost 2.5
// times as much.
#pragma once

#include <Eigen/Core>
#include <boost/random/normal_distribution.hpp>
#include <cstdint>
#include <random>

namespace kinfly::sim {

class NormalRandom {
 public:
  explicit NormalRandom(uint64_t seed) : engine_(seed) {}

  // Standard normal.
  double operator()() { return normal_(engine_); }

  // Three standard normals drawn x, y, z in that order (a constructor's arguments have none).
  Eigen::Vector3d vector3() {
    Eigen::Vector3d v;
    for (int i = 0; i < 3; ++i) v[i] = (*this)();
    return v;
  }

 private:
  std::mt19937_64 engine_;
  boost::random::normal_distribution<double> normal_;
};

}  // namespace kinfly::sim
