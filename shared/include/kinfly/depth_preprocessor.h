// Stage 1-4 of the seed: raw depth -> metres with a validity mask, bilateral filter, 3-level
// discontinuity-aware pyramid, vertex and normal maps per level.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <string>
#include <vector>

#include "kinfly/camera.h"
#include "kinfly/image.h"

namespace kinfly {

constexpr int kPyramidLevels = 3;

// Invalid vertices and normals are NaN vectors, so a single isValid() test covers both.
inline Eigen::Vector3f invalidVector() {
  return Eigen::Vector3f::Constant(std::numeric_limits<float>::quiet_NaN());
}
inline bool isValid(const Eigen::Vector3f& v) { return !std::isnan(v.x()); }

// Four pixels or points at a time, one per lane of an SSE or NEON register, through the GCC/Clang
// vector extensions. The per-pixel kernels of preprocessing and tracking are written once, as
// templates over float (one pixel) and Floats (four along a row), so that vector loops and scalar
// border loops share them. The compiler's own vectoriser cannot do this: the kernels are full of
// selects, and under IEEE trapping semantics it may not compute a side that scalar code skips.
namespace lanes {
typedef float Floats __attribute__((vector_size(16)));
typedef int Ints __attribute__((vector_size(16)));  // lane masks: -1 true, 0 false
constexpr int kWidth = 4;

inline Floats splat(float s) { return Floats{s, s, s, s}; }
// Lanes picked from a (indices 0-3) and b (4-7).
template <int I0, int I1, int I2, int I3>
inline Floats shuffle(Floats a, Floats b) {
#if defined(__clang__)
  return __builtin_shufflevector(a, b, I0, I1, I2, I3);
#else
  return __builtin_shuffle(a, b, Ints{I0, I1, I2, I3});
#endif
}
// One bit per lane of a mask, lane 0 in bit 0.
inline int bits(Ints mask) { return (mask[0] & 1) | (mask[1] & 2) | (mask[2] & 4) | (mask[3] & 8); }

// One value, or four consecutive ones.
template <typename T>
T load(const float* p);
template <>
inline float load<float>(const float* p) {
  return *p;
}
template <>
inline Floats load<Floats>(const float* p) {
  Floats v;
  std::memcpy(&v, p, sizeof v);
  return v;
}
// p[0], or p[0], p[2], p[4], p[6].
template <typename T>
T loadEveryOther(const float* p);
template <>
inline float loadEveryOther<float>(const float* p) {
  return *p;
}
template <>
inline Floats loadEveryOther<Floats>(const float* p) {
  return shuffle<0, 2, 4, 6>(load<Floats>(p), load<Floats>(p + kWidth));
}
inline void store(float* p, float v) { *p = v; }
inline void store(float* p, Floats v) { std::memcpy(p, &v, sizeof v); }
// Pixel coordinate x, or x .. x + 3.
template <typename T>
T coordinate(int x);
template <>
inline float coordinate<float>(int x) {
  return static_cast<float>(x);
}
template <>
inline Floats coordinate<Floats>(int x) {
  const float f = static_cast<float>(x);
  return Floats{f, f + 1.f, f + 2.f, f + 3.f};
}

// a < b ? a : b, NaN giving b: one instruction on SSE, whose minimum is defined this way.
inline float min(float a, float b) { return a < b ? a : b; }
inline Floats min(Floats a, Floats b) {
#if defined(__SSE__)
  return __builtin_ia32_minps(a, b);
#else
  return a < b ? a : b;
#endif
}
inline float abs(float x) { return std::fabs(x); }
inline Floats abs(Floats x) {
  return reinterpret_cast<Floats>(reinterpret_cast<Ints>(x) & 0x7fffffff);
}
inline float sqrt(float x) { return std::sqrt(x); }
inline Floats sqrt(Floats x) {
  for (int l = 0; l < kWidth; ++l) x[l] = std::sqrt(x[l]);  // vectorised by the compiler
  return x;
}
inline int truncate(float x) { return static_cast<int>(x); }
inline Ints truncate(Floats x) { return __builtin_convertvector(x, Ints); }
inline float toFloat(int x) { return static_cast<float>(x); }
inline Floats toFloat(Ints x) { return __builtin_convertvector(x, Floats); }
inline float lookup(const float* table, int i) { return table[i]; }
inline Floats lookup(const float* table, Ints i) {
  typedef unsigned Indices __attribute__((vector_size(16)));  // spares sign-extending each lane
  const Indices u = reinterpret_cast<Indices>(i);
  return Floats{table[u[0]], table[u[1]], table[u[2]], table[u[3]]};
}
// A scalar function applied lane by lane; for short functions the compiler vectorises it.
template <typename F>
Floats lanewise(F f, Floats x) {
  for (int l = 0; l < kWidth; ++l) x[l] = f(x[l]);
  return x;
}
}  // namespace lanes

// The points of one level that the tracker can use (vertex and normal both valid), one image per
// coordinate with each row's points packed to its front: the tracker reads them contiguously,
// skips nothing, and its per-point loops vectorise.
struct PackedPoints {
  // Rows hold a multiple of this many points, so that the tracker's 4-wide loads past a row's
  // last point stay inside the row.
  static constexpr int kRowPadding = lanes::kWidth;
  PackedPoints() = default;
  PackedPoints(int width, int height);
  Image<float> vx, vy, vz;  // [m] camera frame
  Image<float> nx, ny, nz;  // unit, facing the camera
  std::vector<int> row_count;  // points packed into each row
};

// Everything the tracker and integrator need from one depth image. Level 0 is the finest.
struct DepthFrame {
  explicit DepthFrame(const PinholeCamera& level0_camera);

  std::array<PinholeCamera, kPyramidLevels> camera;
  Image<float> raw_depth_m;                               // level 0, unfiltered: integrated into the TSDF
  std::array<Image<float>, kPyramidLevels> depth_m;       // bilateral-filtered, then pyramid
  std::array<Image<Eigen::Vector3f>, kPyramidLevels> vertex_cam;  // [m] camera frame
  std::array<Image<Eigen::Vector3f>, kPyramidLevels> normal_cam;  // unit, facing the camera
  std::array<PackedPoints, kPyramidLevels> points;  // the valid pixels of vertex_cam, normal_cam
};

struct PreprocessResult {
  int valid_pixels = 0;         // level 0, after range limits
  float valid_fraction = 0.f;   // of level-0 pixels
};

// Bilateral weights, tabulated once: the spatial Gaussian per window offset and the range
// Gaussian per depth difference, because an exp() per tap would dominate the frame time.
struct BilateralKernel {
  static constexpr int kMaxRadius = 6;
  static constexpr int kRangeSteps = 64;   // table spans 4 sigma_range; beyond, weight < 3e-4
  BilateralKernel(int radius_px, float sigma_space_px, float sigma_range_m);
  int radius;
  float range_index_per_m;
  std::array<float, (2 * kMaxRadius + 1) * (2 * kMaxRadius + 1)> spatial{};
  // One entry past the table is zero, the weight of any larger difference.
  std::array<float, kRangeSteps + 1> range{};
};

class DepthPreprocessor {
 public:
  struct Params {
    double depth_scale_m = 1.0 / 5000.0;  // [m per raw unit] > 0; TUM 1/5000, OpenNI 1/1000
    float min_depth_m = 0.3f;             // [m] >= 0; Kinect v1 sees nothing nearer than ~0.4 m
    float max_depth_m = 4.0f;             // [m] > min_depth_m; noise grows as z^2 (4 cm at 5 m)
    int downsample = 1;                   // {1, 2, 4}: input subsampling before everything else
    int bilateral_radius_px = 2;          // [px] 0..6; 0 disables the filter
    float bilateral_sigma_space_px = 1.5f;  // [px] > 0
    float bilateral_sigma_range_m = 0.03f;  // [m] > 0; KinFu's 30 mm
    // Pyramid: pixels whose depth differs from the centre by more than this many sigma_range
    // are left out of the average (KinFu pyrDown), so levels do not smear across edges.
    float pyramid_range_sigmas = 3.f;     // > 0

    std::string validate() const;
  };

  // `input_camera` describes the raw images given to process(), before downsampling.
  DepthPreprocessor(const PinholeCamera& input_camera, const Params& params);

  const PinholeCamera& inputCamera() const { return input_camera_; }
  // Camera of pyramid level 0 (after downsampling).
  const PinholeCamera& camera() const { return camera_; }
  const Params& params() const { return params_; }

  // `raw` must be inputCamera().width x height. Never throws on content; all-zero depth gives
  // valid_pixels == 0.
  PreprocessResult process(ImageView<const uint16_t> raw, DepthFrame* frame) const;

 private:
  PinholeCamera input_camera_;
  PinholeCamera camera_;
  Params params_;
  BilateralKernel kernel_;
};

// The stages one pixel or one map at a time: the definitions that process() must reproduce to
// the bit (unit tests check it does). process() filters with a loop that weighs each pair of
// pixels once; the pyramid and maps use the same per-pixel kernels four pixels at a time.
// Invalid (0) taps never contribute, and an invalid centre stays invalid.
float bilateralPixel(ImageView<const float> depth_m, int x, int y, const BilateralKernel& kernel);
// KinFu pyrDown: mean of the valid 5x5 neighbours of fine pixel (2x, 2y) within `max_diff_m` of
// the centre.
float pyrDownPixel(ImageView<const float> fine_m, int x, int y, float max_diff_m);
void computeVertexMap(ImageView<const float> depth_m, const PinholeCamera& camera,
                      ImageView<Eigen::Vector3f> vertex_cam);
void computeNormalMap(ImageView<const Eigen::Vector3f> vertex_cam,
                      ImageView<Eigen::Vector3f> normal_cam);
// Both maps of one level in one pass over its depth image, exactly as the two functions above
// give them, and the valid points packed for the tracker.
void computeVertexNormalMaps(ImageView<const float> depth_m, const PinholeCamera& camera,
                             ImageView<Eigen::Vector3f> vertex_cam,
                             ImageView<Eigen::Vector3f> normal_cam, PackedPoints* points);

}  // namespace kinfly
