// Summary statistics the command-line tools print (timings as median, p90 and p99).
#pragma once

#include <algorithm>
#include <cstddef>
#include <vector>

namespace kinfly::tools {

// The q-quantile (0..1) of `values`, interpolated linearly between order statistics; 0 if empty.
inline double percentile(std::vector<double> values, double q) {
  if (values.empty()) return 0.0;
  std::sort(values.begin(), values.end());
  const double pos = q * static_cast<double>(values.size() - 1);
  const size_t i = static_cast<size_t>(pos);
  const double frac = pos - static_cast<double>(i);
  return i + 1 < values.size() ? values[i] * (1 - frac) + values[i + 1] * frac : values[i];
}

}  // namespace kinfly::tools
