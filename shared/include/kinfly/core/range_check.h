// The one wording of an out-of-range value, for the Params::validate() of the firmware's stages
// and the flight stack:
// "source.speed must be in (0, 100] (got 0)", naming the configuration key, so a refused
// configuration says which key to change and what it may be.
#pragma once

#include <sstream>
#include <string>

#include "kinfly/core/status.h"

namespace kinfly {

enum class Bound { kClosed, kOpen };

// Ok when lo <= value <= hi (lo < value with Bound::kOpen), else the message; NaN is out of
// every range.
inline Status outOfRange(const std::string& key, double value, double lo, double hi,
                              Bound lower = Bound::kClosed) {
  const bool open = lower == Bound::kOpen;
  if ((open ? value > lo : value >= lo) && value <= hi) return {};
  std::ostringstream why;
  why << key << " must be in " << (open ? "(" : "[") << lo << ", " << hi << "] (got " << value
      << ")";
  return Status::error(why.str());
}

// The first failed of several checks, in order: validate() reports one problem at a time.
template <class... Checks>
Status firstError(Checks&&... checks) {
  Status first;
  ((first.ok() ? void(first = std::forward<Checks>(checks)) : void()), ...);
  return first;
}

}  // namespace kinfly
