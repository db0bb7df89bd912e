// The array types kinfly_ground._native's parts share, and 4x4 poses to and from numpy.
#pragma once

#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>

#include <cstdint>

#include "kinfly/core/se3.h"

namespace kinfly::native {

namespace nb = nanobind;

using DepthIn = nb::ndarray<const uint16_t, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using DepthOut = nb::ndarray<nb::numpy, uint16_t, nb::ndim<2>>;
using PoseIn = nb::ndarray<const double, nb::shape<4, 4>, nb::c_contig, nb::device::cpu>;
using PoseOut = nb::ndarray<nb::numpy, double, nb::shape<4, 4>>;

// A 4x4 camera-to-world matrix from Python, its rotation re-orthonormalised.
inline Pose poseOf(const PoseIn& T) {
  Pose pose = Pose::Identity();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) pose.matrix()(r, c) = T(r, c);
  return orthonormalized(pose);
}

inline PoseOut matrixOf(const Pose& pose) {
  auto* m = new double[16];
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) m[4 * r + c] = pose.matrix()(r, c);
  return PoseOut(m, {4, 4},
                 nb::capsule(m, [](void* p) noexcept { delete[] static_cast<double*>(p); }));
}

// The link's bindings (native_link.cpp): channels, receiving, signing, the engine's camera and
// tracking status.
void bindLink(nb::module_& m);

}  // namespace kinfly::native
