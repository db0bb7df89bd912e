// The simulator's one source of randomness: normal deviates whose sequence is fixed by the seed
// alone, on any standard library. mt19937_64's output is fixed by the C++ standard, but
// std::normal_distribution's algorithm is each library's own choice, so the deviates are drawn
// here (Box-Muller) and a flight gives the same figures for its seed wherever it runs.
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <random>
#include <vector>

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
    const double u_radius = uniform();
    const double u_angle = uniform();
    double first = 0.0;
    boxMuller(u_radius, u_angle, &first, &spare_);
    has_spare_ = true;
    return first;
  }

  // The next n deviates into out: the same numbers, in the same order, as n calls of operator().
  // The uniforms are drawn here in order; their transform (a logarithm, a sine and a cosine a
  // pair, most of the cost) is handed to for_each_pair(pairs, transform), which must call
  // transform(begin, end) on parts that cover [0, pairs) once each, in any order and on any
  // threads, and return when all have finished (they write out, and the spare).
  template <class ForEachPair>
  void fill(double* out, size_t n, ForEachPair&& for_each_pair) {
    size_t k = 0;
    if (has_spare_ && n > 0) {
      out[k++] = spare_;
      has_spare_ = false;
    }
    const size_t pairs = (n - k + 1) / 2;
    uniforms_.resize(2 * pairs);
    for (double& u : uniforms_) u = uniform();
    double last_second = 0.0;  // of the last pair, when n leaves it over as the spare
    for_each_pair(pairs, [&](size_t begin, size_t end) {
      for (size_t j = begin; j < end; ++j) {
        const size_t at = k + 2 * j;
        double second = 0.0;
        boxMuller(uniforms_[2 * j], uniforms_[2 * j + 1], &out[at], &second);
        if (at + 1 < n) {
          out[at + 1] = second;
        } else {
          last_second = second;
        }
      }
    });
    if (k + 2 * pairs > n) {
      spare_ = last_second;
      has_spare_ = true;
    }
  }

  // Three standard normals drawn x, y, z in that order (a constructor's arguments have none).
  Eigen::Vector3d vector3() {
    Eigen::Vector3d v;
    for (int i = 0; i < 3; ++i) v[i] = (*this)();
    return v;
  }

 private:
  static void boxMuller(double u_radius, double u_angle, double* first, double* second) {
    const double radius = std::sqrt(-2.0 * std::log(1.0 - u_radius));  // 1 - u is in (0, 1]
    const double angle = 2.0 * M_PI * u_angle;
    *first = radius * std::cos(angle);
    *second = radius * std::sin(angle);
  }

  std::mt19937_64 engine_;
  std::vector<double> uniforms_;  // fill's, kept between calls
  double spare_ = 0.0;
  bool has_spare_ = false;
};

}  // namespace kinfly::sim
