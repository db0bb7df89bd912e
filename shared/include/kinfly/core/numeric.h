// Small numeric helpers used inside per-pixel and per-voxel loops.
#pragma once

namespace kinfly {

// Round half away from zero. std::lround is an out-of-line libm call that costs more than the
// rest of a projective association step; this compiles to a few instructions.
inline int roundToInt(float x) { return static_cast<int>(x >= 0.f ? x + 0.5f : x - 0.5f); }

// floor() for values well inside int range, without a libm call.
inline int floorToInt(float x) {
  const int i = static_cast<int>(x);
  return i - (static_cast<float>(i) > x);
}

}  // namespace kinfly
