// The range check of a per-axis parameter, for the flight stack's validate(): each component is
// named as the configuration key names it, "rate.p_gain_1_s.roll" or "position.p_gain_1_s2.x".
#pragma once

#include <Eigen/Core>
#include <array>
#include <string>

#include "kinfly/core/range_check.h"

namespace kinfly::flight {

using AxisNames = std::array<const char*, 3>;
constexpr AxisNames kBodyAxes = {"roll", "pitch", "yaw"};
constexpr AxisNames kWorldAxes = {"x", "y", "z"};

inline Status axesInRange(const std::string& key, const Eigen::Vector3d& value,
                          const AxisNames& axes, double lo, double hi,
                          Bound lower = Bound::kClosed) {
  return firstError(outOfRange(key + "." + axes[0], value(0), lo, hi, lower),
                    outOfRange(key + "." + axes[1], value(1), lo, hi, lower),
                    outOfRange(key + "." + axes[2], value(2), lo, hi, lower));
}

}  // namespace kinfly::flight
