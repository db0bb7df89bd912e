#include "kinfly/preprocessing/depth_preprocessor.h"

#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>
#include <sstream>
#include "parallel.h"

namespace kinfly {

Status DepthPreprocessor::Params::validate() const {
  std::ostringstream why;
  if (!(depth_scale_m > 0.0 && std::isfinite(depth_scale_m))) why << "depth_scale_m must be > 0";
  else if (!(min_depth_m >= 0.f)) why << "min_depth_m must be >= 0";
  else if (!(max_depth_m > min_depth_m)) why << "max_depth_m must be > min_depth_m";
  else if (downsample != 1 && downsample != 2 && downsample != 4) why << "downsample must be 1, 2 or 4";
  else if (bilateral_radius_px < 0 || bilateral_radius_px > BilateralKernel::kMaxRadius)
    why << "bilateral_radius_px must be in [0, " << BilateralKernel::kMaxRadius << "]";
  else if (!(bilateral_sigma_space_px > 0.f)) why << "bilateral_sigma_space_px must be > 0";
  else if (!(bilateral_sigma_range_m > 0.f)) why << "bilateral_sigma_range_m must be > 0";
  else if (!(pyramid_range_sigmas > 0.f)) why << "pyramid_range_sigmas must be > 0";
  return why.str().empty() ? Status() : Status::error(why.str());
}

BilateralKernel::BilateralKernel(int radius_px, float sigma_space_px, float sigma_range_m)
    : radius(std::clamp(radius_px, 0, kMaxRadius)) {
  const int side = 2 * radius + 1;
  for (int dy = -radius; dy <= radius; ++dy)
    for (int dx = -radius; dx <= radius; ++dx)
      spatial[(dy + radius) * side + dx + radius] =
          std::exp(-static_cast<float>(dx * dx + dy * dy) / (2.f * sigma_space_px * sigma_space_px));
  const float span_m = 4.f * sigma_range_m;
  range_index_per_m = kRangeSteps / span_m;
  for (int i = 0; i < kRangeSteps; ++i) {
    const float d = (static_cast<float>(i) + 0.5f) / range_index_per_m;
    range[i] = std::exp(-d * d / (2.f * sigma_range_m * sigma_range_m));
  }
  range[kRangeSteps] = 0.f;
}

namespace {

using lanes::Floats;
using lanes::kWidth;

// Index into the range table for the depth difference of two pixels: kRangeSteps (weight zero)
// for anything past the table, clamped before the conversion so that any difference converts.
template <typename T>
auto rangeBin(T a, T b, const BilateralKernel& k) {
  constexpr float kSteps = static_cast<float>(BilateralKernel::kRangeSteps);
  return lanes::truncate(lanes::min(lanes::abs(a - b) * k.range_index_per_m, T{} + kSteps));
}

// Where one tap of a row of output pixels reads its depth and its weight, for the first pixel;
// the next pixels read on along the row.
struct Tap {
  const float* depth;
  const float* weight;
};

// Filters G groups of four pixels from column c on. The groups' sums are independent, which
// hides the latency of each add.
template <int G>
void filterGroups(const Tap* taps, int n_taps, const float* centre, int c, float* out) {
  Floats sum[G] = {}, weight_sum[G] = {};
  for (int t = 0; t < n_taps; ++t)
    for (int g = 0; g < G; ++g) {
      const Floats weight = lanes::load<Floats>(taps[t].weight + c + kWidth * g);
      sum[g] += weight * lanes::load<Floats>(taps[t].depth + c + kWidth * g);
      weight_sum[g] += weight;
    }
  for (int g = 0; g < G; ++g) {
    const Floats d = lanes::load<Floats>(centre + c + kWidth * g);
    lanes::store(out + c + kWidth * g, d > 0.f ? sum[g] / weight_sum[g] : 0.f);
  }
}

// The bilateral filter over a band of rows, four pixels at a time, to the bit what
// bilateralPixel gives. A pair of pixels has the same weight whichever is the centre (spatial
// and range weights are both symmetric), so each pair is weighed once, for the forward half of
// the window (offsets after the centre in scan order), and kept for the rows below that read it
// back. Invalid pixels, and those outside the image, are read as a depth so far away that a pair
// with one valid pixel falls past the range table and weighs zero, the taps bilateralPixel
// leaves out; pairs of two invalid pixels only reach invalid centres, which give 0 whatever
// their sums. Taps are summed in bilateralPixel's order, the left-out ones adding exact zeros.
void bilateralBand(ImageView<const float> depth_m, int y_begin, int y_end,
                   const BilateralKernel& k, ImageView<float> out) {
  const int w = depth_m.width(), h = depth_m.height();
  const int r = k.radius, side = 2 * r + 1;
  const int forward = r * (side + 1);  // r offsets right of the centre, r full rows below
  auto forwardIndex = [&](int dx, int dy) {
    return dy == 0 ? dx - 1 : r + (dy - 1) * side + dx + r;
  };
  auto spatial = [&](int dx, int dy) { return k.spatial[(dy + r) * side + dx + r]; };
  constexpr int kMaxR = BilateralKernel::kMaxRadius;
  // Each forward offset's spatial weight times the range table, so that weighing a pair is one
  // lookup: the same product, to the bit, as multiplying after the lookup.
  constexpr int kBins = BilateralKernel::kRangeSteps + 1;
  float forward_weights[kMaxR * (2 * kMaxR + 2)][kBins];
  for (int dy = 0; dy <= r; ++dy)
    for (int dx = dy == 0 ? 1 : -r; dx <= r; ++dx)
      for (int i = 0; i < kBins; ++i)
        forward_weights[forwardIndex(dx, dy)][i] = spatial(dx, dy) * k.range[i];
  // Rows are kept in rings whose sizes are powers of two, so that a row's slot is a mask of its
  // index. The weights kept for r + 1 rows fill a fixed buffer; the tile width follows from it.
  auto powerOfTwo = [](int n) { int p = 1; while (p < n) p *= 2; return p; };
  const int ring_rows = powerOfTwo(r + 1), depth_rows = powerOfTwo(side);
  constexpr int kRingFloats = 16384, kMaxTile = 128;
  static_assert(kMaxR <= 7, "the rings of kept rows have at most 8 and 16 slots");
  static_assert(kRingFloats / (8 * kMaxR * (2 * kMaxR + 2)) - 2 * kMaxR - kWidth >= kWidth,
                "the largest radius needs a tile of at least four pixels");
  const int tile = std::min(kMaxTile, (kRingFloats / (ring_rows * forward) - 2 * r - kWidth) /
                                          kWidth * kWidth);
  const int ring_row = tile + 2 * r + kWidth;  // weights of columns x0 - r .. x0 + tile + r
  float ring[kRingFloats];
  // Depth rows y - r .. y + r, columns x0 - 2r .. x0 + tile + 2r.
  constexpr int kDepthRow = kMaxTile + 4 * kMaxR + 2 * kWidth;
  float depth[16][kDepthRow];
  auto depthRow = [&](int y) { return depth[y & (depth_rows - 1)]; };
  auto ringRow = [&](int y, int j) {
    return ring + ((y & (ring_rows - 1)) * forward + j) * ring_row;
  };
  // A pixel's own weight: no distance, no difference.
  float centre_weight[kMaxTile];
  std::fill(centre_weight, centre_weight + kMaxTile, spatial(0, 0) * k.range[0]);

  constexpr float kFar = -1e9f;  // [m] the depth invalid pixels are read as
  for (int x0 = 0; x0 < w; x0 += tile) {
    // The output columns of this tile, and the groups of four that cover them: the last tile of
    // a row is weighed only as far as its groups read.
    const int n = std::min(tile, w - x0);
    const int groups_end = (n + kWidth - 1) / kWidth * kWidth;
    auto loadDepth = [&](int y) {
      float* row = depthRow(y);
      std::fill(row, row + kDepthRow, kFar);
      if (y < 0 || y >= h) return;
      const int lo = std::max(x0 - 2 * r, 0), hi = std::min(x0 + tile + 2 * r + kWidth, w);
      for (int x = lo; x < hi; ++x) {
        const float d = depth_m(x, y);
        row[x - (x0 - 2 * r)] = d > 0.f ? d : kFar;
      }
    };
    for (int y = y_begin - 2 * r; y < y_begin; ++y) loadDepth(y);
    for (int y = y_begin - r; y < y_end; ++y) {
      loadDepth(y + r);
      // Weights of row y's pixels with their forward neighbours.
      const float* here = depthRow(y) + r;
      for (int dy = 0; dy <= r; ++dy)
        for (int dx = dy == 0 ? 1 : -r; dx <= r; ++dx) {
          const float* there = depthRow(y + dy) + r + dx;
          float* weights = ringRow(y, forwardIndex(dx, dy));
          const float* table = forward_weights[forwardIndex(dx, dy)];
          // All of the row's bins first, so that the lookups read their indices from memory.
          int bins[kMaxTile + 2 * kMaxR + kWidth];
          for (int i = 0; i < groups_end + 2 * r; i += kWidth)
            lanes::store(bins + i, rangeBin(lanes::load<Floats>(there + i),
                                            lanes::load<Floats>(here + i), k));
          for (int i = 0; i < groups_end + 2 * r; i += kWidth)
            lanes::store(weights + i, lanes::lookup(table, bins + i));
        }
      if (y < y_begin) continue;
      // Row y of the output: where each tap, in scan order, reads its depth and weight.
      Tap taps[(2 * kMaxR + 1) * (2 * kMaxR + 1)];
      for (int dy = -r, t = 0; dy <= r; ++dy)
        for (int dx = -r; dx <= r; ++dx, ++t) {
          taps[t].depth = depthRow(y + dy) + 2 * r + dx;
          if (dy < 0 || (dy == 0 && dx < 0))  // weighed from the tap's side, in its row
            taps[t].weight = ringRow(y + dy, forwardIndex(-dx, -dy)) + r + dx;
          else if (dx == 0 && dy == 0)
            taps[t].weight = centre_weight;
          else
            taps[t].weight = ringRow(y, forwardIndex(dx, dy)) + r;
        }
      const float* centre = depthRow(y) + 2 * r;
      float filtered[kMaxTile];
      int c = 0;
      for (; c + 4 * kWidth <= n; c += 4 * kWidth)
        filterGroups<4>(taps, side * side, centre, c, filtered);
      for (; c < n; c += kWidth) filterGroups<1>(taps, side * side, centre, c, filtered);
      std::copy(filtered, filtered + n, out.row(y) + x0);
    }
  }
}

// KinFu pyrDown at coarse (x, y); for T = Floats at (x .. x + 3, y), whose windows must then lie
// inside the image.
template <typename T>
T pyrDown(ImageView<const float> fine_m, int x, int y, float max_diff_m) {
  const int fx = 2 * x, fy = 2 * y;
  const T centre = lanes::loadEveryOther<T>(fine_m.row(fy) + fx);
  const int x0 = std::max(fx - 2, 0), x1 = std::min(fx + 2, fine_m.width() - 1);
  const int y0 = std::max(fy - 2, 0), y1 = std::min(fy + 2, fine_m.height() - 1);
  T sum{};
  decltype(lanes::truncate(T{})) count{};
  for (int qy = y0; qy <= y1; ++qy) {
    const float* row = fine_m.row(qy);
    for (int qx = x0; qx <= x1; ++qx) {
      const T d = lanes::loadEveryOther<T>(row + qx);
      const auto counts = (d > 0.f) & (lanes::abs(d - centre) < max_diff_m);
      sum += counts ? d : 0.f;
      count += counts & 1;  // true is 1 for one pixel, -1 in a lane
    }
  }
  return centre > 0.f ? sum / lanes::toFloat(count) : 0.f;  // a valid centre counts itself
}

template <typename T>
struct Vec3 {
  T x, y, z;
};

// v(u) = D(u) K^-1 [u, 1], with PinholeCamera::backProject's arithmetic; zero depth gives a
// finite vertex that the callers mark invalid.
template <typename T>
Vec3<T> backProject(const PinholeCamera& c, T u, float v, T d) {
  return {(u - c.cx) * d / c.fx, (v - c.cy) * d / c.fy, d};
}

// n(u) = (v(x+1,y) - v(x,y)) x (v(x,y+1) - v(x,y)), normalised, with Eigen's arithmetic for
// 3-vectors; `defined` says where the cross product does not vanish.
template <typename T, typename Mask>
Vec3<T> normal(const Vec3<T>& v, const Vec3<T>& right, const Vec3<T>& below, Mask* defined) {
  const Vec3<T> a{right.x - v.x, right.y - v.y, right.z - v.z};
  const Vec3<T> b{below.x - v.x, below.y - v.y, below.z - v.z};
  const Vec3<T> c{a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
  const T len = lanes::sqrt(c.x * c.x + (c.y * c.y + c.z * c.z));
  *defined = len > 0.f;
  const Vec3<T> n{c.x / len, c.y / len, c.z / len};
  // The raw cross product faces away from the camera (x right, y down, z forward); flip it so
  // model and frame normals share the raycaster's convention.
  const auto away = n.x * v.x + (n.y * v.y + n.z * v.z) > 0.f;
  return {away ? -n.x : n.x, away ? -n.y : n.y, away ? -n.z : n.z};
}

// One row of an image from a per-pixel kernel, called with a float tag for one pixel and a Floats
// tag for four: four at a time where the kernel's windows lie inside the image (rows where
// `interior_row`, and groups starting at columns lo .. hi), one at a time elsewhere.
template <typename Kernel>
void kernelRow(int width, int lo, int hi, bool interior_row, Kernel kernel, float* out) {
  int x = 0;
  if (interior_row) {
    for (; x < lo; ++x) lanes::store(out + x, kernel(x, float{}));
    for (; x <= hi; x += kWidth) lanes::store(out + x, kernel(x, Floats{}));
  }
  for (; x < width; ++x) lanes::store(out + x, kernel(x, float{}));
}

}  // namespace

float bilateralPixel(ImageView<const float> depth_m, int x, int y, const BilateralKernel& k) {
  const float centre = depth_m(x, y);
  if (centre <= 0.f) return 0.f;
  const int r = k.radius;
  const int side = 2 * r + 1;
  const int x0 = std::max(x - r, 0), x1 = std::min(x + r, depth_m.width() - 1);
  const int y0 = std::max(y - r, 0), y1 = std::min(y + r, depth_m.height() - 1);
  float sum = 0.f, weight_sum = 0.f;
  for (int qy = y0; qy <= y1; ++qy) {
    const float* row = depth_m.row(qy);
    const float* spatial = &k.spatial[(qy - y + r) * side];
    for (int qx = x0; qx <= x1; ++qx) {
      const float d = row[qx];
      // Invalid taps (0) are far from any valid centre, but test explicitly: a centre near the
      // minimum range must not pull in zeros.
      if (d <= 0.f) continue;
      const float w = spatial[qx - x + r] * k.range[rangeBin(d, centre, k)];
      sum += w * d;
      weight_sum += w;
    }
  }
  return sum / weight_sum;  // the centre itself always contributes, so weight_sum > 0
}

float pyrDownPixel(ImageView<const float> fine_m, int x, int y, float max_diff_m) {
  return pyrDown<float>(fine_m, x, y, max_diff_m);
}

void computeVertexMap(ImageView<const float> depth_m, const PinholeCamera& camera,
                      ImageView<Eigen::Vector3f> vertex_cam) {
  forEachStatic(depth_m.height(), [&](int y) {
    const float* d = depth_m.row(y);
    Eigen::Vector3f* v = vertex_cam.row(y);
    for (int x = 0; x < depth_m.width(); ++x) {
      const Vec3<float> p = backProject(camera, static_cast<float>(x), static_cast<float>(y), d[x]);
      v[x] = d[x] > 0.f ? Eigen::Vector3f(p.x, p.y, p.z) : invalidVector();
    }
  });
}

void computeNormalMap(ImageView<const Eigen::Vector3f> vertex_cam,
                      ImageView<Eigen::Vector3f> normal_cam) {
  const int w = vertex_cam.width(), h = vertex_cam.height();
  forEachStatic(h, [&](int y) {
    Eigen::Vector3f* n = normal_cam.row(y);
    for (int x = 0; x < w; ++x) {
      n[x] = invalidVector();
      if (x + 1 >= w || y + 1 >= h) continue;
      const Eigen::Vector3f& v = vertex_cam(x, y);
      const Eigen::Vector3f& vx = vertex_cam(x + 1, y);
      const Eigen::Vector3f& vy = vertex_cam(x, y + 1);
      if (!isValid(v) || !isValid(vx) || !isValid(vy)) continue;
      bool defined;
      const Vec3<float> c = normal<float>({v.x(), v.y(), v.z()}, {vx.x(), vx.y(), vx.z()},
                                          {vy.x(), vy.y(), vy.z()}, &defined);
      if (defined) n[x] = {c.x, c.y, c.z};
    }
  });
}

void computePackedPoints(ImageView<const float> depth_m, const PinholeCamera& camera,
                         PackedPoints* points) {
  const int w = depth_m.width(), h = depth_m.height();
  // A band of rows is done a tile of columns at a time, top to bottom, so that each row's
  // vertices are computed once and serve as the lower neighbours of the row above. A tile's
  // vertices reach one group past it, for the right neighbours; past the image they have zero
  // depth, which makes them invalid.
  constexpr int kBandRows = 32, kTile = 64;
  struct VertexRow {
    float x[kTile + kWidth], y[kTile + kWidth], z[kTile + kWidth];  // z is the depth
    Vec3<Floats> at(int i) const {
      return {lanes::load<Floats>(x + i), lanes::load<Floats>(y + i), lanes::load<Floats>(z + i)};
    }
  };
  auto backProjectRow = [&](int y, int x0, VertexRow* row) {
    const int in_image = y < h ? std::min(kTile + kWidth, w - x0) : 0;
    const float* depth = depth_m.row(std::min(y, h - 1)) + x0;
    for (int i = 0; i < kTile + kWidth; i += kWidth) {
      Floats d{};
      if (i + kWidth <= in_image)
        d = lanes::load<Floats>(depth + i);
      else
        for (int l = 0; i + l < in_image; ++l) d[l] = depth[i + l];
      const Vec3<Floats> p = backProject(camera, lanes::coordinate<Floats>(x0 + i),
                                         static_cast<float>(y), d);
      lanes::store(row->x + i, p.x), lanes::store(row->y + i, p.y), lanes::store(row->z + i, p.z);
    }
  };
  forEachStatic((h + kBandRows - 1) / kBandRows, [&](int band) {
    const int y0 = band * kBandRows, y1 = std::min(y0 + kBandRows, h);
    std::fill(points->row_count.begin() + y0, points->row_count.begin() + y1, 0);
    for (int x0 = 0; x0 < w; x0 += kTile) {
      const int n = std::min(kTile, w - x0);
      VertexRow rows[2];
      backProjectRow(y0, x0, &rows[0]);
      for (int y = y0; y < y1; ++y) {
        const VertexRow& here = rows[(y - y0) % 2];
        VertexRow& below = rows[(y - y0 + 1) % 2];
        backProjectRow(y + 1, x0, &below);
        float* packed[6] = {points->vx.view().row(y), points->vy.view().row(y),
                            points->vz.view().row(y), points->nx.view().row(y),
                            points->ny.view().row(y), points->nz.view().row(y)};
        int& count = points->row_count[y];
        for (int i = 0; i < n; i += kWidth) {
          const Vec3<Floats> v = here.at(i), right = here.at(i + 1), down = below.at(i);
          lanes::Ints defined;
          const Vec3<Floats> c = normal(v, right, down, &defined);
          const lanes::Ints has_normal =
              (v.z > 0.f) & (right.z > 0.f) & (down.z > 0.f) & defined;
          const int m = std::min(kWidth, n - i);
          // Points with a normal go to the front of the row: all four at once where they can.
          const Floats values[6] = {v.x, v.y, v.z, c.x, c.y, c.z};
          const int packs = lanes::bits(has_normal) & ((1 << m) - 1);
          if (packs == (1 << kWidth) - 1) {
            for (int k = 0; k < 6; ++k) lanes::store(packed[k] + count, values[k]);
            count += kWidth;
            continue;
          }
          for (int l = 0; l < m; ++l)
            if (packs & (1 << l)) {
              for (int k = 0; k < 6; ++k) packed[k][count] = values[k][l];
              ++count;
            }
        }
      }
    }
  });
}

DepthPreprocessor::DepthPreprocessor(const PinholeCamera& input_camera, const Params& params)
    : input_camera_(input_camera),
      camera_(input_camera.scaled(params.downsample)),
      params_(params),
      kernel_(params.bilateral_radius_px, params.bilateral_sigma_space_px,
              params.bilateral_sigma_range_m) {}

PreprocessResult DepthPreprocessor::process(ImageView<const uint16_t> raw, DepthFrame* frame) const {
  const int ds = params_.downsample;
  const int w = camera_.width, h = camera_.height;
  const float scale = static_cast<float>(params_.depth_scale_m);
  const float lo = params_.min_depth_m, hi = params_.max_depth_m;
  ImageView<float> raw_m = frame->raw_depth_m.view();
  const int valid = sumStatic(h, [&](int y) {
    const uint16_t* in = raw.row(y * ds);
    float* out = raw_m.row(y);
    int row_valid = 0;
    for (int x = 0; x < w; ++x) {
      const float d = static_cast<float>(in[x * ds]) * scale;
      const bool ok = (d >= lo) & (d <= hi) & (d > 0.f);
      out[x] = ok ? d : 0.f;
      row_valid += ok;
    }
    return row_valid;
  });

  ImageView<float> filtered = frame->depth_m[0].view();
  if (kernel_.radius == 0) {
    frame->depth_m[0].copyFrom(raw_m);
  } else {
    constexpr int kBandRows = 32;  // each band also weighs the radius' rows above it
    forEachStatic((h + kBandRows - 1) / kBandRows, [&](int band) {
      const int y = band * kBandRows;
      bilateralBand(raw_m, y, std::min(y + kBandRows, h), kernel_, filtered);
    });
  }

  const float max_diff_m = params_.pyramid_range_sigmas * params_.bilateral_sigma_range_m;
  for (int l = 1; l < kPyramidLevels; ++l) {
    ImageView<const float> fine = frame->depth_m[l - 1].view();
    ImageView<float> coarse = frame->depth_m[l].view();
    // Four coarse pixels from x use fine columns 2x - 2 .. 2x + 8; their loads touch 2x + 9.
    forEachStatic(coarse.height(), [&](int y) {
      kernelRow(coarse.width(), 1, (fine.width() - 10) / 2, 2 * y >= 2 && 2 * y + 2 < fine.height(),
                [&](int x, auto tag) { return pyrDown<decltype(tag)>(fine, x, y, max_diff_m); },
                coarse.row(y));
    });
  }
  for (int l = 0; l < kPyramidLevels; ++l)
    computePackedPoints(frame->depth_m[l].view(), frame->camera[l], &frame->points[l]);
  return {valid, static_cast<float>(valid) / static_cast<float>(w * h)};
}

}  // namespace kinfly
