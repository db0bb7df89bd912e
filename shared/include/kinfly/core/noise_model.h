// Depth noise of structured-light sensors (Kinect v1, Xtion): the seed's model, after Nguyen,
// Izadi and Lovell (2012). Axial sigma grows with the square of range: ~1.5 mm at 1 m, ~4 cm at 5 m.
#pragma once

namespace kinfly {

inline float kinectNoiseSigmaM(float z_m) {
  const float d = z_m - 0.4f;
  return 0.0012f + 0.0019f * d * d;
}

}  // namespace kinfly
