#include "kinfly/raycast/raycaster.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cmath>

#include <limits>
#include <sstream>

#include "kinfly/core/numeric.h"
#include "kinfly/volume/voxel_reader.h"
#include "parallel.h"

namespace kinfly {

namespace {

// How Newton's method from a measured depth ended.
enum class Newton {
  kHit,
  // The trilinear cell at the measurement has an unobserved corner: the measurement lies on the
  // edge of what the map has seen (a silhouette, the frustum's or the dense window's border).
  kUnobservedStart,
  kGaveUp,  // elsewhere: a truncated, flat or back-facing field, or the iterate left the range
};

// The search along one pixel's ray, in voxel units: p(z) = origin_vox + ray_vox * z, where z is
// the depth in metres and ray_vox the voxels travelled per metre of depth.
struct RaySearch {
  Eigen::Vector3f origin_vox;
  float mu_vox;         // truncation band [voxels]
  float step_fraction;  // of the band, for steps through observed space

  // Newton's method on the trilinear TSDF, started at the depth just measured (which the TSDF
  // has just fused, so the surface is usually within a voxel of it): mostly one sample, instead
  // of a march. Gives up when the field there is unobserved, truncated or not a front face, or
  // when the iterate leaves [z_min, z_max].
  Newton newton(VoxelReader* reader, const Eigen::Vector3f& ray_vox, float z_start, float z_min,
                float z_max, float* z_hit, Eigen::Vector3f* gradient) const {
    constexpr int kMaxIterations = 4;
    // An update shorter than this is taken without sampling again: along a ray the trilinear
    // field is a cubic that is nearly linear over a voxel, so the step's own error is second
    // order (the unit test holds it to the march's accuracy). A twentieth of a voxel costs a
    // second sample for nearly every pixel and a quarter more raycast time, for no gain in
    // tracking (ATE 0.747 vs 0.738 cm on the TUM teddy sequence).
    constexpr float kToleranceVox = 0.5f;
    const float tolerance_z = kToleranceVox / ray_vox.norm();
    float z = z_start;
    for (int it = 0; it < kMaxIterations; ++it) {
      float f;
      if (!reader->trilinear(origin_vox + ray_vox * z, &f, gradient))
        return it == 0 ? Newton::kUnobservedStart : Newton::kGaveUp;
      // Inside the band |f| < 1; at the clamp the field is flat and says nothing about distance.
      if (std::fabs(f) >= 1.f) return Newton::kGaveUp;
      const float slope = gradient->dot(ray_vox);  // dTSDF/dz; negative through a front face
      if (!(slope < 0.f)) return Newton::kGaveUp;
      const float dz = -f / slope;
      z += dz;
      if (!(z >= z_min && z <= z_max)) return Newton::kGaveUp;
      if (std::fabs(dz) < tolerance_z) {
        *z_hit = z;
        return gradient->squaredNorm() > 0.f ? Newton::kHit : Newton::kGaveUp;
      }
    }
    return Newton::kGaveUp;
  }

  // KinectFusion's march: steps bounded by the TSDF through observed space, whole unallocated
  // blocks skipped, the sign change found on nearest voxels, then bracketed on the trilinear
  // field and refined by regula falsi.
  bool march(VoxelReader* reader, const Eigen::Vector3f& ray_vox, float z_begin, float z_end,
             float* z_hit, Eigen::Vector3f* gradient) const {
    const float vox_per_z = ray_vox.norm();
    const Eigen::Vector3f inv_dir = ray_vox.cwiseInverse();
    const float far_step_vox = mu_vox * step_fraction;
    float z = z_begin, prev_z = 0.f, prev_f = 0.f;
    bool prev_known = false;
    while (z <= z_end) {
      const Eigen::Vector3f p = origin_vox + ray_vox * z;
      const int gx = roundToInt(p.x()), gy = roundToInt(p.y()), gz = roundToInt(p.z());
      const Voxel* voxel = reader->voxel(gx, gy, gz);
      if (voxel == nullptr) {
        // An unallocated block holds no surface: jump to where the ray leaves the region whose
        // nearest voxels belong to it, [8b - 0.5, 8b + 7.5) per axis.
        const Eigen::Vector3f lo(static_cast<float>((gx >> 3) * kBlockSide) - 0.5f,
                                 static_cast<float>((gy >> 3) * kBlockSide) - 0.5f,
                                 static_cast<float>((gz >> 3) * kBlockSide) - 0.5f);
        float z_exit = std::numeric_limits<float>::infinity();
        for (int a = 0; a < 3; ++a) {
          if (ray_vox[a] == 0.f) continue;
          const float bound = ray_vox[a] > 0.f ? lo[a] + kBlockSide : lo[a];
          z_exit = std::min(z_exit, (bound - origin_vox[a]) * inv_dir[a]);
        }
        prev_known = false;
        z = std::max(z_exit, z) + 0.01f / vox_per_z;  // a hundredth of a voxel past the face
        continue;
      }
      const bool known = voxel->weight > 0.f;
      const float f = voxel->tsdf;
      if (known && prev_known && prev_f > 0.f && f <= 0.f)
        return refine(reader, ray_vox, prev_z, prev_f, z, f, z_hit, gradient);
      // Left a surface from behind.
      if (known && prev_known && prev_f < 0.f && f > 0.f) return false;
      prev_known = known;
      prev_f = f;
      prev_z = z;
      // In observed space the TSDF bounds the distance to the surface; elsewhere step by a
      // fraction of the band so no crossing is jumped over.
      const float step_vox = known ? std::max(1.f, f * mu_vox * step_fraction) : far_step_vox;
      z += step_vox / vox_per_z;
    }
    return false;
  }

  // A sign change between nearest voxels at depths z0 (f0 > 0) and z1 (f1 <= 0). Brackets it on
  // the trilinear field (stepping out by up to two voxels where the interpolated signs disagree
  // with the nearest ones), then refines by regula falsi: the nearest-voxel interpolation alone is
  // only good to half a voxel.
  bool refine(VoxelReader* reader, const Eigen::Vector3f& ray_vox, float z0, float f0_nearest,
              float z1, float f1_nearest, float* z_hit, Eigen::Vector3f* gradient) const {
    const float voxel_z = 1.f / ray_vox.norm();
    float za = z0, zb = z1, f0 = 0.f, f1 = 0.f;
    bool ok = reader->trilinear(origin_vox + ray_vox * za, &f0, nullptr) &&
              reader->trilinear(origin_vox + ray_vox * zb, &f1, nullptr);
    for (int k = 0; ok && f0 <= 0.f && k < 2; ++k) {
      za -= voxel_z;
      ok = reader->trilinear(origin_vox + ray_vox * za, &f0, nullptr);
    }
    for (int k = 0; ok && f1 > 0.f && k < 2; ++k) {
      zb += voxel_z;
      ok = reader->trilinear(origin_vox + ray_vox * zb, &f1, nullptr);
    }
    float z = z0 + (z1 - z0) * f0_nearest / (f0_nearest - f1_nearest);
    if (ok && f0 > 0.f && f1 <= 0.f) {
      // The trilinear field is nearly linear across one cell: two secant steps bring the
      // bracket well under a twentieth of a voxel, and each costs a trilinear sample.
      for (int it = 0; it < 2 && (zb - za) > 0.05f * voxel_z; ++it) {
        z = za + (zb - za) * f0 / (f0 - f1);
        float fm;
        if (!reader->trilinear(origin_vox + ray_vox * z, &fm, nullptr)) break;
        if (fm > 0.f) {
          za = z;
          f0 = fm;
        } else {
          zb = z;
          f1 = fm;
        }
      }
    }
    float f_hit;
    if (!reader->trilinear(origin_vox + ray_vox * z, &f_hit, gradient) ||
        !(gradient->squaredNorm() > 0.f))
      return false;
    *z_hit = z;
    return true;
  }
};

}  // namespace

bool sampleTsdf(const TsdfVolume& volume, const Eigen::Vector3f& p_world, float* tsdf,
                Eigen::Vector3f* gradient) {
  VoxelReader reader(volume);
  return reader.trilinear(p_world / volume.voxelSizeM(), tsdf, gradient);
}

Status Raycaster::Params::validate() const {
  std::ostringstream why;
  if (!(min_depth_m >= 0.f)) why << "min_depth_m must be >= 0";
  else if (!(max_depth_m > min_depth_m)) why << "max_depth_m must be > min_depth_m";
  else if (!(step_fraction > 0.f && step_fraction <= 1.f)) why << "step_fraction must be in (0, 1]";
  else if (range_tile_px < 1) why << "range_tile_px must be >= 1";
  else if (!(hint_margin_m > 0.f)) why << "hint_margin_m must be > 0";
  return why.str().empty() ? Status() : Status::error(why.str());
}

Raycaster::Raycaster(const PinholeCamera& camera, const Params& params)
    : camera_(camera),
      params_(params),
      tile_range_((camera.width + params.range_tile_px - 1) / params.range_tile_px,
                  (camera.height + params.range_tile_px - 1) / params.range_tile_px,
                  Eigen::Vector2f::Zero()),
      column_vox_(static_cast<size_t>(camera.width)),
      row_vox_(static_cast<size_t>(camera.height)) {
  for (int x = 0; x < camera.width; ++x)
    ray_x_.push_back(camera.backProject(static_cast<float>(x), 0.f, 1.f).x());
  for (int y = 0; y < camera.height; ++y)
    ray_y_.push_back(camera.backProject(0.f, static_cast<float>(y), 1.f).y());
}

void Raycaster::computeRanges(const TsdfVolume& volume, const Pose& T_cam_world) {
  const float inf = std::numeric_limits<float>::infinity();
  tile_range_.fill(Eigen::Vector2f(inf, 0.f));
  const Eigen::Matrix3f R = T_cam_world.linear().cast<float>();
  const Eigen::Vector3f t = T_cam_world.translation().cast<float>();
  const float bs = volume.blockSizeM(), vs = volume.voxelSizeM();
  const float near = params_.min_depth_m, far = params_.max_depth_m;
  const int tiles_x = tile_range_.width(), tiles_y = tile_range_.height();
  const float inv_tile = 1.f / static_cast<float>(params_.range_tile_px);
  for (const VoxelBlock* blk : volume.allocatedBlocks()) {
    // The block's voxel centres span [origin, origin + 7 voxels]; trilinear samples reach one
    // voxel further into the next block, so the box covers a whole block size.
    const Eigen::Vector3f lo =
        volume.voxelCentre(blk->index, 0, 0, 0) - Eigen::Vector3f::Constant(0.5f * vs);
    float zmin = inf, zmax = -inf, umin = inf, umax = -inf, vmin = inf, vmax = -inf;
    bool behind = false;
    for (int c = 0; c < 8; ++c) {
      const Eigen::Vector3f corner = lo + Eigen::Vector3f((c & 1) ? bs : 0.f, (c & 2) ? bs : 0.f,
                                                          (c & 4) ? bs : 0.f);
      const Eigen::Vector3f p = R * corner + t;
      zmin = std::min(zmin, p.z());
      zmax = std::max(zmax, p.z());
      if (p.z() < near) {
        behind = true;
        continue;
      }
      const Eigen::Vector2f uv = camera_.project(p);
      umin = std::min(umin, uv.x()); umax = std::max(umax, uv.x());
      vmin = std::min(vmin, uv.y()); vmax = std::max(vmax, uv.y());
    }
    if (zmax < near || zmin > far) continue;
    int tx0 = 0, tx1 = tiles_x - 1, ty0 = 0, ty1 = tiles_y - 1;
    if (!behind) {  // a block cut by the near plane may cover any part of the image
      tx0 = std::max(0, static_cast<int>(std::floor(umin * inv_tile)));
      tx1 = std::min(tiles_x - 1, static_cast<int>(std::floor(umax * inv_tile)));
      ty0 = std::max(0, static_cast<int>(std::floor(vmin * inv_tile)));
      ty1 = std::min(tiles_y - 1, static_cast<int>(std::floor(vmax * inv_tile)));
    }
    for (int ty = ty0; ty <= ty1; ++ty)
      for (int tx = tx0; tx <= tx1; ++tx) {
        Eigen::Vector2f& r = tile_range_(tx, ty);
        r.x() = std::min(r.x(), zmin);
        r.y() = std::max(r.y(), zmax);
      }
  }
}

RaycastResult Raycaster::raycast(const TsdfVolume& volume, float truncation_m,
                                 const Pose& T_world_cam, ModelMaps* maps,
                                 ImageView<const float> depth_hint_m) {
  const bool use_hint = !depth_hint_m.empty();
  // The maps, the hint and this raycaster's tables are one camera's (a model at another pyramid
  // level has a raycaster of its own size: FusionPipeline::Params::model_level).
  assert(maps->vertex_ref[0].width() == camera_.width && maps->vertex_ref[0].height() == camera_.height);
  assert(!use_hint || (depth_hint_m.width() == camera_.width && depth_hint_m.height() == camera_.height));
  // Tile ranges cost a pass over every allocated block, which grows with the map; a hinted ray
  // already knows its range.
  if (!use_hint) computeRanges(volume, T_world_cam.inverse());
  const Eigen::Matrix3f R_wc = T_world_cam.linear().cast<float>();
  const Eigen::Matrix3f R_cw = R_wc.transpose();
  const float inv_vs = 1.f / volume.voxelSizeM();
  const Eigen::Vector3f origin_vox = T_world_cam.translation().cast<float>() * inv_vs;
  const RaySearch ray{origin_vox, truncation_m * inv_vs, params_.step_fraction};
  for (int x = 0; x < camera_.width; ++x) column_vox_[x] = R_wc.col(0) * (ray_x_[x] * inv_vs);
  for (int y = 0; y < camera_.height; ++y)
    row_vox_[y] = (R_wc.col(1) * ray_y_[y] + R_wc.col(2)) * inv_vs;
  const int tile = params_.range_tile_px;
  ImageView<Eigen::Vector3f> vmap = maps->vertex_ref[0].view();
  ImageView<Eigen::Vector3f> nmap = maps->normal_ref[0].view();
  maps->normal_spacing_m = volume.voxelSizeM();
  const int hits = sumDynamic(camera_.height, 4, [&](int y) {
    VoxelReader reader(volume);
    int row_hits = 0;
    Eigen::Vector3f* vertex_row = vmap.row(y);
    Eigen::Vector3f* normal_row = nmap.row(y);
    const float* hint_row = use_hint ? depth_hint_m.row(y) : nullptr;
    for (int x = 0; x < camera_.width; ++x) {
      vertex_row[x] = invalidVector();
      normal_row[x] = invalidVector();
      const float hint = use_hint ? hint_row[x] : 0.f;
      if (use_hint && !(hint > 0.f)) continue;
      const Eigen::Vector2f range = use_hint ? Eigen::Vector2f(hint - params_.hint_margin_m,
                                                               hint + params_.hint_margin_m)
                                             : tile_range_(x / tile, y / tile);
      const float z_begin = std::max(range.x(), params_.min_depth_m);
      const float z_end = std::min(range.y(), params_.max_depth_m);
      if (!(z_begin < z_end)) continue;
      const Eigen::Vector3f ray_cam(ray_x_[x], ray_y_[y], 1.f);
      const Eigen::Vector3f ray_vox = column_vox_[x] + row_vox_[y];  // voxels per metre of depth
      float z_hit = 0.f;
      Eigen::Vector3f grad;
      // A measurement on the edge of the observed field is not marched from: the march seldom
      // finds a surface there, and then mostly centimetres from where the frame measured, which
      // is where the next frame's measurements associate (docs/engine.md, departure 4).
      const Newton newton = use_hint
                                ? ray.newton(&reader, ray_vox, hint, z_begin, z_end, &z_hit, &grad)
                                : Newton::kGaveUp;
      const bool hit = newton == Newton::kHit ||
                       (newton == Newton::kGaveUp &&
                        ray.march(&reader, ray_vox, z_begin, z_end, &z_hit, &grad));
      if (hit) {
        vertex_row[x] = ray_cam * z_hit;
        normal_row[x] = (R_cw * grad).normalized();
        ++row_hits;
      }
    }
    return row_hits;
  });
  return {hits, static_cast<float>(hits) / static_cast<float>(camera_.width * camera_.height)};
}

void Raycaster::shade(ImageView<const Eigen::Vector3f> vertex_cam,
                      ImageView<const Eigen::Vector3f> normal_cam, ImageView<uint8_t> out) {
  constexpr float kAmbient = 0.15f;  // keeps surfaces seen edge-on distinguishable from holes
  forEachStatic(out.height(), [&](int y) {
    for (int x = 0; x < out.width(); ++x) {
      const Eigen::Vector3f& v = vertex_cam(x, y);
      const Eigen::Vector3f& n = normal_cam(x, y);
      if (!isValid(v) || !isValid(n)) {
        out(x, y) = 0;
        continue;
      }
      const float lambert = std::max(0.f, -n.dot(v.normalized()));
      out(x, y) = static_cast<uint8_t>(255.f * (kAmbient + (1.f - kAmbient) * lambert));
    }
  });
}

}  // namespace kinfly
