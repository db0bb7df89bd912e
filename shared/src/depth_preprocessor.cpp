#include "kinfly/depth_preprocessor.h"

#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>
#include <sstream>

namespace kinfly {

namespace {
int paddedWidth(int width) {
  return (width + PackedPoints::kRowPadding - 1) / PackedPoints::kRowPadding * PackedPoints::kRowPadding;
}
}  // namespace

PackedPoints::PackedPoints(int width, int height)
    : vx(paddedWidth(width), height),
      vy(paddedWidth(width), height),
      vz(paddedWidth(width), height),
      nx(paddedWidth(width), height),
      ny(paddedWidth(width), height),
      nz(paddedWidth(width), height),
      row_count(static_cast<size_t>(height), 0) {}

DepthFrame::DepthFrame(const PinholeCamera& level0_camera)
    : raw_depth_m(level0_camera.width, level0_camera.height, 0.f) {
  for (int l = 0; l < kPyramidLevels; ++l) {
    camera[l] = level0_camera.scaled(1 << l);
    depth_m[l] = Image<float>(camera[l].width, camera[l].height, 0.f);
    vertex_cam[l] = Image<Eigen::Vector3f>(camera[l].width, camera[l].height, invalidVector());
    normal_cam[l] = Image<Eigen::Vector3f>(camera[l].width, camera[l].height, invalidVector());
    points[l] = PackedPoints(camera[l].width, camera[l].height);
  }
}

std::string DepthPreprocessor::Params::validate() const {
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
  return why.str();
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
}

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
      const int bin = static_cast<int>(std::fabs(d - centre) * k.range_index_per_m);
      // Invalid taps (0) are far from any valid centre, but test explicitly: a centre near
      // the minimum range must not pull in zeros.
      if (d <= 0.f || bin >= BilateralKernel::kRangeSteps) continue;
      const float w = spatial[qx - x + r] * k.range[bin];
      sum += w * d;
      weight_sum += w;
    }
  }
  return sum / weight_sum;  // the centre itself always contributes, so weight_sum > 0
}

float pyrDownPixel(ImageView<const float> fine_m, int x, int y, float max_diff_m) {
  const int fx = 2 * x, fy = 2 * y;
  const float centre = fine_m(fx, fy);
  if (centre <= 0.f) return 0.f;
  const int x0 = std::max(fx - 2, 0), x1 = std::min(fx + 2, fine_m.width() - 1);
  const int y0 = std::max(fy - 2, 0), y1 = std::min(fy + 2, fine_m.height() - 1);
  float sum = 0.f;
  int count = 0;
  for (int qy = y0; qy <= y1; ++qy) {
    const float* row = fine_m.row(qy);
    for (int qx = x0; qx <= x1; ++qx) {
      const float d = row[qx];
      if (d > 0.f && std::fabs(d - centre) < max_diff_m) {
        sum += d;
        ++count;
      }
    }
  }
  return sum / static_cast<float>(count);
}

void computeVertexMap(ImageView<const float> depth_m, const PinholeCamera& camera,
                      ImageView<Eigen::Vector3f> vertex_cam) {
#pragma omp parallel for schedule(static)
  for (int y = 0; y < depth_m.height(); ++y) {
    const float* d = depth_m.row(y);
    Eigen::Vector3f* v = vertex_cam.row(y);
    for (int x = 0; x < depth_m.width(); ++x)
      v[x] = d[x] > 0.f ? camera.backProject(static_cast<float>(x), static_cast<float>(y), d[x])
                        : invalidVector();
  }
}

void computeNormalMap(ImageView<const Eigen::Vector3f> vertex_cam,
                      ImageView<Eigen::Vector3f> normal_cam) {
  const int w = vertex_cam.width(), h = vertex_cam.height();
#pragma omp parallel for schedule(static)
  for (int y = 0; y < h; ++y) {
    Eigen::Vector3f* n = normal_cam.row(y);
    for (int x = 0; x < w; ++x) {
      n[x] = invalidVector();
      if (x + 1 >= w || y + 1 >= h) continue;
      const Eigen::Vector3f& v = vertex_cam(x, y);
      const Eigen::Vector3f& vx = vertex_cam(x + 1, y);
      const Eigen::Vector3f& vy = vertex_cam(x, y + 1);
      if (!isValid(v) || !isValid(vx) || !isValid(vy)) continue;
      Eigen::Vector3f c = (vx - v).cross(vy - v);
      const float len = c.norm();
      if (!(len > 0.f)) continue;
      c /= len;
      // The raw cross product faces away from the camera (x right, y down, z forward); flip it
      // so model and frame normals share the raycaster's convention.
      n[x] = c.dot(v) > 0.f ? Eigen::Vector3f(-c) : c;
    }
  }
}

void packPoints(ImageView<const Eigen::Vector3f> vertex_cam,
                ImageView<const Eigen::Vector3f> normal_cam, PackedPoints* points) {
  const int w = vertex_cam.width(), h = vertex_cam.height();
#pragma omp parallel for schedule(static)
  for (int y = 0; y < h; ++y) {
    const Eigen::Vector3f* v = vertex_cam.row(y);
    const Eigen::Vector3f* n = normal_cam.row(y);
    float *vx = points->vx.view().row(y), *vy = points->vy.view().row(y),
          *vz = points->vz.view().row(y), *nx = points->nx.view().row(y),
          *ny = points->ny.view().row(y), *nz = points->nz.view().row(y);
    int count = 0;
    for (int x = 0; x < w; ++x) {
      if (!isValid(v[x]) || !isValid(n[x])) continue;
      vx[count] = v[x].x();
      vy[count] = v[x].y();
      vz[count] = v[x].z();
      nx[count] = n[x].x();
      ny[count] = n[x].y();
      nz[count] = n[x].z();
      ++count;
    }
    points->row_count[y] = count;
  }
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
  int valid = 0;
  ImageView<float> raw_m = frame->raw_depth_m.view();
#pragma omp parallel for schedule(static) reduction(+ : valid)
  for (int y = 0; y < h; ++y) {
    const uint16_t* in = raw.row(y * ds);
    float* out = raw_m.row(y);
    for (int x = 0; x < w; ++x) {
      const float d = static_cast<float>(in[x * ds]) * scale;
      const bool ok = d >= lo && d <= hi && d > 0.f;
      out[x] = ok ? d : 0.f;
      valid += ok;
    }
  }

  ImageView<float> filtered = frame->depth_m[0].view();
  if (kernel_.radius == 0) {
    frame->depth_m[0].copyFrom(raw_m);
  } else {
#pragma omp parallel for schedule(static)
    for (int y = 0; y < h; ++y) {
      float* out = filtered.row(y);
      for (int x = 0; x < w; ++x) out[x] = bilateralPixel(raw_m, x, y, kernel_);
    }
  }

  const float max_diff_m = params_.pyramid_range_sigmas * params_.bilateral_sigma_range_m;
  for (int l = 1; l < kPyramidLevels; ++l) {
    ImageView<const float> fine = frame->depth_m[l - 1].view();
    ImageView<float> coarse = frame->depth_m[l].view();
#pragma omp parallel for schedule(static)
    for (int y = 0; y < coarse.height(); ++y)
      for (int x = 0; x < coarse.width(); ++x) coarse(x, y) = pyrDownPixel(fine, x, y, max_diff_m);
  }
  for (int l = 0; l < kPyramidLevels; ++l) {
    computeVertexMap(frame->depth_m[l].view(), frame->camera[l], frame->vertex_cam[l].view());
    computeNormalMap(frame->vertex_cam[l].view(), frame->normal_cam[l].view());
    packPoints(frame->vertex_cam[l].view(), frame->normal_cam[l].view(), &frame->points[l]);
  }
  return {valid, static_cast<float>(valid) / static_cast<float>(w * h)};
}

}  // namespace kinfly
