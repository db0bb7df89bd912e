// kinfly_ground._native: the engine in shared/ and the link (native_link.cpp) for Python. Input arrays are read in place; a
// decoded image is copied once out of the codec's reused buffer into the array handed over, and a
// mesh's vectors are handed over without a copy. The heavy calls release the GIL, so the LCM
// thread keeps receiving while a keyframe is fused.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/array.h>
#include <nanobind/stl/string.h>
#include <omp.h>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <cstring>
#include <memory>
#include <mutex>
#include <string>
#include <utility>
#include <vector>

#include "arrays.h"
#include "kinfly/core/camera.h"
#include "kinfly/codec/depth_codec.h"
#include "kinfly/link/chunking.h"
#include "kinfly/mesh/incremental_mesher.h"
#include "kinfly/pipeline/fusion_pipeline.h"
#include "kinfly/mesh/mesh.h"
#include "kinfly/volume/tsdf_volume.h"

namespace nb = nanobind;
using kinfly::CodecResult;
using kinfly::DepthCodec;
using kinfly::DepthEncoding;
using kinfly::native::DepthIn;
using kinfly::native::DepthOut;
using kinfly::native::matrixOf;
using kinfly::native::poseOf;
using kinfly::native::PoseIn;

namespace {

using GrayOut = nb::ndarray<nb::numpy, uint8_t, nb::ndim<2>>;
using Rows3f = nb::ndarray<nb::numpy, float, nb::ndim<2>>;
using Rows3i = nb::ndarray<nb::numpy, int32_t, nb::ndim<2>>;
template <typename T>
using RowsIn = nb::ndarray<const T, nb::shape<-1, 3>, nb::c_contig, nb::device::cpu>;

// Rows of three as Eigen 3-vectors, for a mesh assembled in Python (the submaps' meshes, moved).
template <typename Vec, typename T>
std::vector<Vec> vectorsOf(const RowsIn<T>& rows) {
  static_assert(sizeof(Vec) == 3 * sizeof(T));
  const Vec* first = reinterpret_cast<const Vec*>(rows.data());
  return std::vector<Vec>(first, first + rows.shape(0));
}

// Arrays handed to Python own a heap object through a capsule.
template <typename T>
nb::capsule ownerOf(T* object) {
  return nb::capsule(object, [](void* p) noexcept { delete static_cast<T*>(p); });
}

// Vector3f/Vector3i are three packed scalars, so a std::vector of them is an N x 3 array: a
// view of it, kept alive by OWNER.
template <typename Array, typename Vec>
Array rowsOf(std::vector<Vec>& values, nb::handle owner) {
  static_assert(sizeof(Vec) == 3 * sizeof(typename Vec::Scalar));
  return Array(values.data(), {values.size(), 3}, owner);
}

DepthEncoding encodingOf(int value) {
  if (value < 0 || value >= kinfly::kDepthEncodingCount)
    throw nb::value_error(("unknown depth encoding " + std::to_string(value)).c_str());
  return static_cast<DepthEncoding>(value);
}

void check(const CodecResult& result, const char* what) {
  if (!result.ok())
    throw nb::value_error((std::string(what) + ": " + kinfly::toString(result.status) +
                           (*result.detail ? std::string(" (") + result.detail + ")" : ""))
                              .c_str());
}

// One codec object per Python object: it keeps its zstd contexts and buffers between frames.
class PyDepthCodec {
 public:
  PyDepthCodec(int encoding, int zstd_level, int max_width_px, int max_height_px) {
    DepthCodec::Params params;
    params.encoding = encodingOf(encoding);
    params.zstd_level = zstd_level;
    params.max_width_px = max_width_px;
    params.max_height_px = max_height_px;
    if (const kinfly::Status valid = params.validate(); !valid.ok())
      throw nb::value_error(valid.message().c_str());
    codec_ = std::make_unique<DepthCodec>(params);
  }

  nb::bytes encode(DepthIn depth) {
    const kinfly::ImageView<const uint16_t> view(depth.data(), static_cast<int>(depth.shape(1)),
                                                 static_cast<int>(depth.shape(0)));
    check(codec_->encode(view, &payload_), "cannot encode depth");
    return nb::bytes(reinterpret_cast<const char*>(payload_.data()), payload_.size());
  }

  DepthOut decode(nb::bytes payload, int encoding, int width, int height) {
    check(codec_->decode(reinterpret_cast<const uint8_t*>(payload.c_str()), payload.size(),
                         encodingOf(encoding), width, height, &depth_),
          "cannot decode depth");
    auto* pixels = new uint16_t[depth_.numPixels()];
    std::memcpy(pixels, depth_.data(), depth_.numPixels() * sizeof(uint16_t));
    nb::capsule owner(pixels, [](void* p) noexcept { delete[] static_cast<uint16_t*>(p); });
    return DepthOut(pixels, {static_cast<size_t>(height), static_cast<size_t>(width)}, owner);
  }

 private:
  std::unique_ptr<DepthCodec> codec_;
  std::vector<uint8_t> payload_;
  kinfly::Image<uint16_t> depth_;
};

// A map's mesh, kept per block and brought up to date with the blocks changed since the last
// snapshot (kinfly::IncrementalMesher), shared by a Fusion and the snapshots it handed out.
// Fusion.snapshot(), on the thread that fuses (the map does not change meanwhile), copies only
// the changed blocks and the neighbours meshing them reads (collect) under `delta_mutex`;
// MapSnapshot.mesh(), on any thread, takes what was collected and meshes it under `mesh_mutex`
// alone, so fusion never waits for marching cubes. A snapshot never meshed leaves its blocks to
// the next one: nothing collected is lost, and deltas are meshed in the order collected.
struct MeshState {
  std::mutex delta_mutex;
  kinfly::MeshChangeTracker tracker;  // under delta_mutex
  kinfly::MeshDelta pending;          // under delta_mutex: collected, not meshed yet
  std::mutex mesh_mutex;
  kinfly::IncrementalMesher mesher{kinfly::IncrementalMesher::Params()};  // under mesh_mutex
};

// The map at a snapshot, meshed on its own while the original goes on fusing. The mesh is
// assembled once (the viewer and the PLY file share it) and handed out as views owned by the
// snapshot. It is the map as of this snapshot, or of a later one taken before this one was
// meshed (the station's mesher skips to the newest).
class PyMapSnapshot {
 public:
  PyMapSnapshot(std::shared_ptr<MeshState> state, size_t num_blocks)
      : state_(std::move(state)), num_blocks_(num_blocks) {}

  nb::tuple mesh(nb::handle self) {
    {
      nb::gil_scoped_release unlocked;
      extract();
    }
    return nb::make_tuple(rowsOf<Rows3f>(mesh_.vertices, self), rowsOf<Rows3i>(mesh_.triangles, self),
                          rowsOf<Rows3f>(mesh_.normals, self));
  }

  size_t numBlocks() const { return num_blocks_; }

  // How the mesh was brought up to date (None before mesh()).
  nb::object update() const {
    if (!extracted_.load()) return nb::none();
    nb::dict d;
    d["map_blocks"] = update_.map_blocks;
    d["blocks_changed"] = update_.blocks_changed;
    d["blocks_remeshed"] = update_.blocks_remeshed;
    d["blocks_kept"] = update_.blocks_kept;
    d["collect_ms"] = update_.collect_ms;
    d["mesh_ms"] = update_.mesh_ms;
    return d;
  }

 private:
  // Once, whichever thread asks first: the station's mesher and its loop checks may mesh one
  // closed submap's snapshot at the same time, and both read mesh_ afterwards.
  void extract() {
    std::lock_guard<std::mutex> once(extract_mutex_);
    if (extracted_.load()) return;
    kinfly::MeshDelta delta;
    std::lock_guard<std::mutex> meshing(state_->mesh_mutex);
    {
      std::lock_guard<std::mutex> collecting(state_->delta_mutex);
      std::swap(delta, state_->pending);
    }
    // One thread, at the mesher thread's low priority: fusion keeps the cores.
    update_ = state_->mesher.apply(&delta, /*parallel=*/false);
    state_->mesher.assemble(&mesh_);
    extracted_ = true;
  }

  std::shared_ptr<MeshState> state_;
  size_t num_blocks_;
  kinfly::TriangleMesh mesh_;
  kinfly::MeshUpdateResult update_;
  std::mutex extract_mutex_;
  std::atomic<bool> extracted_{false};
};

struct RefineResult {
  kinfly::TrackingStatus status = kinfly::TrackingStatus::kLost;
  kinfly::Pose T_world_cam = kinfly::Pose::Identity();
  float inlier_fraction = 0.f;
  float rmse_m = 0.f;
  float valid_depth_fraction = 0.f;
  std::string lost_reason;
  double preprocess_ms = 0, track_ms = 0, integrate_ms = 0, raycast_ms = 0, total_ms = 0;
};

// What a parameter struct's validate() says, as Python sees it: "" when valid, otherwise why.
std::string whyInvalid(const kinfly::Status& status) {
  return status.ok() ? std::string() : status.message();
}

void throwIfInvalid(const kinfly::Status& status) {
  if (!status.ok()) throw nb::value_error(status.message().c_str());
}

// One map: a hashed volume and the pipeline that tracks and fuses into it at full resolution,
// made from the engine's own parameter structs (the station builds them, kinfly_ground/station.py).
class PyFusion {
 public:
  PyFusion(const kinfly::PinholeCamera& camera, const kinfly::HashedVolume::Params& volume,
           const kinfly::FusionPipeline::Params& pipeline, int threads)
      : threads_(threads) {
    if (threads < 1) throw nb::value_error("threads must be at least 1");
    throwIfInvalid(camera.validate());
    throwIfInvalid(volume.validate());
    throwIfInvalid(pipeline.validate(volume.voxel_size_m));
    volume_ = std::make_unique<kinfly::HashedVolume>(volume);
    pipeline_ = std::make_unique<kinfly::FusionPipeline>(camera, pipeline, volume_.get());
  }

  RefineResult refine(DepthIn depth, int64_t utime, PoseIn T_world_cam_guess) {
    checkSize(depth);
    const kinfly::Pose guess = poseOf(T_world_cam_guess);
    kinfly::FrameResult r;
    {
      nb::gil_scoped_release unlocked;
      omp_set_num_threads(threads_);  // per calling thread: the worker, not the caller's others
      r = pipeline_->processFrameFromGuess(viewOf(depth), utime, guess);
    }
    return resultOf(r);
  }

  RefineResult fuseAt(DepthIn depth, int64_t utime, PoseIn T_world_cam) {
    checkSize(depth);
    const kinfly::Pose pose = poseOf(T_world_cam);
    kinfly::FrameResult r;
    {
      nb::gil_scoped_release unlocked;
      omp_set_num_threads(threads_);
      r = pipeline_->processFrameAtPose(viewOf(depth), utime, pose);
    }
    return resultOf(r);
  }

  static RefineResult resultOf(const kinfly::FrameResult& r) {
    RefineResult out{r.status, r.T_world_cam};
    out.inlier_fraction = r.inlier_fraction;
    out.rmse_m = r.rmse_m;
    out.valid_depth_fraction = r.valid_depth_fraction;
    out.lost_reason = r.lost_reason;
    out.preprocess_ms = r.ms.preprocess;
    out.track_ms = r.ms.track;
    out.integrate_ms = r.ms.integrate;
    out.raycast_ms = r.ms.raycast;
    out.total_ms = r.ms.total;
    return out;
  }

  // full: a raycast of every pixel (slow at full resolution); otherwise the per-frame model
  // maps shaded, where the last refined keyframe measured depth (fuse_at raycasts nothing).
  GrayOut render(bool full) {
    const kinfly::PinholeCamera& camera = full ? pipeline_->camera() : pipeline_->model().camera[0];
    auto* image = new kinfly::Image<uint8_t>(camera.width, camera.height, 0);
    {
      nb::gil_scoped_release unlocked;
      omp_set_num_threads(threads_);
      if (full)
        pipeline_->renderShaded(image->view());
      else
        pipeline_->shadeModel(image->view());
    }
    return GrayOut(image->data(), {static_cast<size_t>(camera.height), static_cast<size_t>(camera.width)},
                   ownerOf(image));
  }

  // The map to mesh beside the fusion: copies the blocks changed since the last snapshot and
  // their neighbours (call it where the map is not being changed: the fusing thread).
  PyMapSnapshot* snapshot() {
    nb::gil_scoped_release unlocked;
    std::lock_guard<std::mutex> collecting(mesh_->delta_mutex);
    mesh_->tracker.collect(*volume_, /*copy=*/true, &mesh_->pending);
    return new PyMapSnapshot(mesh_, volume_->numAllocatedBlocks());
  }

  size_t numBlocks() const { return volume_->numAllocatedBlocks(); }
  size_t memoryBytes() const { return volume_->memoryBytes(); }
  float voxelSizeM() const { return volume_->voxelSizeM(); }

 private:
  void checkSize(const DepthIn& depth) const {
    const kinfly::PinholeCamera& camera = pipeline_->inputCamera();
    if (static_cast<int>(depth.shape(1)) != camera.width || static_cast<int>(depth.shape(0)) != camera.height)
      throw nb::value_error(("depth image is " + std::to_string(depth.shape(1)) + "x" +
                             std::to_string(depth.shape(0)) + ", the map's camera " +
                             std::to_string(camera.width) + "x" + std::to_string(camera.height))
                                .c_str());
  }
  static kinfly::ImageView<const uint16_t> viewOf(const DepthIn& depth) {
    return kinfly::ImageView<const uint16_t>(depth.data(), static_cast<int>(depth.shape(1)),
                                             static_cast<int>(depth.shape(0)));
  }

  int threads_;
  std::unique_ptr<kinfly::HashedVolume> volume_;
  std::unique_ptr<kinfly::FusionPipeline> pipeline_;
  std::shared_ptr<MeshState> mesh_ = std::make_shared<MeshState>();
};

// The engine's parameter structs, their fields named as in the engine (units and ranges at each
// field in its header) and their validate(): "" when valid, otherwise why.
void bindParams(nb::module_& m) {
  using kinfly::DepthPreprocessor;
  using kinfly::FusionPipeline;
  using kinfly::HashedVolume;
  using kinfly::IcpTracker;
  using kinfly::Raycaster;
  using kinfly::TsdfIntegrator;
  nb::class_<HashedVolume::Params>(m, "HashedVolumeParams",
                                   "The ground's map (volume/tsdf_volume.h, HashedVolume::Params)")
      .def(nb::init<>())
      .def_rw("voxel_size_m", &HashedVolume::Params::voxel_size_m)
      .def_rw("chunk_blocks", &HashedVolume::Params::chunk_blocks)
      .def("validate", [](const HashedVolume::Params& p) { return whyInvalid(p.validate()); });

  nb::class_<DepthPreprocessor::Params>(
      m, "DepthPreprocessorParams",
      "Depth conversion, filter and pyramid (preprocessing/depth_preprocessor.h)")
      .def(nb::init<>())
      .def_rw("depth_scale_m", &DepthPreprocessor::Params::depth_scale_m)
      .def_rw("min_depth_m", &DepthPreprocessor::Params::min_depth_m)
      .def_rw("max_depth_m", &DepthPreprocessor::Params::max_depth_m)
      .def_rw("downsample", &DepthPreprocessor::Params::downsample)
      .def_rw("bilateral_radius_px", &DepthPreprocessor::Params::bilateral_radius_px)
      .def_rw("bilateral_sigma_space_px", &DepthPreprocessor::Params::bilateral_sigma_space_px)
      .def_rw("bilateral_sigma_range_m", &DepthPreprocessor::Params::bilateral_sigma_range_m)
      .def_rw("pyramid_range_sigmas", &DepthPreprocessor::Params::pyramid_range_sigmas)
      .def("validate", [](const DepthPreprocessor::Params& p) { return whyInvalid(p.validate()); });

  nb::class_<IcpTracker::Params>(m, "IcpTrackerParams", "Frame-to-model ICP (tracking/icp_tracker.h)")
      .def(nb::init<>())
      .def_rw("iterations_coarse_to_fine", &IcpTracker::Params::iterations_coarse_to_fine)
      .def_rw("distance_gate_m", &IcpTracker::Params::distance_gate_m)
      .def_rw("normal_angle_gate_rad", &IcpTracker::Params::normal_angle_gate_rad)
      .def_rw("normal_gate_sigmas", &IcpTracker::Params::normal_gate_sigmas)
      .def_rw("min_inlier_fraction", &IcpTracker::Params::min_inlier_fraction)
      .def_rw("min_inliers", &IcpTracker::Params::min_inliers)
      .def_rw("weak_direction_fraction", &IcpTracker::Params::weak_direction_fraction)
      .def_rw("max_weak_directions", &IcpTracker::Params::max_weak_directions)
      .def_rw("max_translation_m", &IcpTracker::Params::max_translation_m)
      .def_rw("max_rotation_rad", &IcpTracker::Params::max_rotation_rad)
      .def_rw("max_rmse_m", &IcpTracker::Params::max_rmse_m)
      .def_rw("max_rmse_sigmas", &IcpTracker::Params::max_rmse_sigmas)
      .def_rw("noise_weighting", &IcpTracker::Params::noise_weighting)
      .def_rw("huber_sigmas", &IcpTracker::Params::huber_sigmas)
      .def_rw("convergence_epsilon", &IcpTracker::Params::convergence_epsilon)
      .def("validate", [](const IcpTracker::Params& p) { return whyInvalid(p.validate()); });

  nb::class_<TsdfIntegrator::Params>(m, "TsdfIntegratorParams",
                                     "TSDF integration (volume/tsdf_integrator.h)")
      .def(nb::init<>())
      .def_rw("truncation_m", &TsdfIntegrator::Params::truncation_m)
      .def_rw("max_weight", &TsdfIntegrator::Params::max_weight)
      .def_rw("allocation_stride_px", &TsdfIntegrator::Params::allocation_stride_px)
      .def("validate", [](const TsdfIntegrator::Params& p, float voxel_size_m) {
        return whyInvalid(p.validate(voxel_size_m));
      }, nb::arg("voxel_size_m"));

  nb::class_<Raycaster::Params>(m, "RaycasterParams", "Raycasting the model (raycast/raycaster.h)")
      .def(nb::init<>())
      .def_rw("min_depth_m", &Raycaster::Params::min_depth_m)
      .def_rw("max_depth_m", &Raycaster::Params::max_depth_m)
      .def_rw("step_fraction", &Raycaster::Params::step_fraction)
      .def_rw("range_tile_px", &Raycaster::Params::range_tile_px)
      .def_rw("hint_margin_m", &Raycaster::Params::hint_margin_m)
      .def("validate", [](const Raycaster::Params& p) { return whyInvalid(p.validate()); });

  // The stages' structs are reached through it and changed in place
  // (p.integrate.truncation_m = 0.04).
  nb::class_<FusionPipeline::Params>(m, "FusionPipelineParams",
                                     "The loop's stages (pipeline/fusion_pipeline.h)")
      .def(nb::init<>())
      .def_rw("preprocess", &FusionPipeline::Params::preprocess)
      .def_rw("icp", &FusionPipeline::Params::icp)
      .def_rw("integrate", &FusionPipeline::Params::integrate)
      .def_rw("raycast", &FusionPipeline::Params::raycast)
      .def_rw("model_level", &FusionPipeline::Params::model_level)
      .def_rw("min_valid_depth_fraction", &FusionPipeline::Params::min_valid_depth_fraction)
      .def_rw("max_recovery_gate_scale", &FusionPipeline::Params::max_recovery_gate_scale)
      .def_rw("max_prior_disagreement_m", &FusionPipeline::Params::max_prior_disagreement_m)
      .def_rw("max_prior_disagreement_rad", &FusionPipeline::Params::max_prior_disagreement_rad)
      .def_rw("relocalise", &FusionPipeline::Params::relocalise)
      .def("validate", [](const FusionPipeline::Params& p, float voxel_size_m) {
        return whyInvalid(p.validate(voxel_size_m));
      }, nb::arg("voxel_size_m"));
}

}  // namespace

NB_MODULE(_native, m) {
  m.doc() = "kinfly's engine (shared/) for the ground station";
  // Python does not promise to destroy every object before it exits (an uncaught exception's
  // traceback keeps the station alive), so nanobind's exit-time leak report would be noise.
  nb::set_leak_warnings(false);
  // Loading the module loaded libcm256cc, whose constructor flushed denormals to zero for the
  // importing thread and every thread it makes later (chunking.h): numpy and the engine too.
  kinfly::link::restoreIeeeFloatingPoint();
  kinfly::native::bindLink(m);
  m.def("rotation_angle_rad",
        [](PoseIn T) { return kinfly::rotationAngleRad(poseOf(T)); }, nb::arg("T"),
        "Rotation angle of a 4x4 rigid transform in [0, pi] (se3.h's atan2 form: exact for small "
        "angles, unlike acos of the trace)");
  m.def(
      "write_ply",
      [](const std::string& path, RowsIn<float> vertices, RowsIn<int32_t> triangles,
         RowsIn<float> normals) {
        if (normals.shape(0) != vertices.shape(0)) {
          throw nb::value_error("write_ply: one normal per vertex");
        }
        kinfly::TriangleMesh mesh;
        mesh.vertices = vectorsOf<Eigen::Vector3f>(vertices);
        mesh.normals = vectorsOf<Eigen::Vector3f>(normals);
        mesh.triangles = vectorsOf<Eigen::Vector3i>(triangles);
        kinfly::Status written;
        {
          nb::gil_scoped_release unlocked;
          written = kinfly::writePly(mesh, path);
        }
        if (!written.ok()) {
          PyErr_SetString(PyExc_OSError, written.message().c_str());
          throw nb::python_error();
        }
        return mesh.triangles.size();
      },
      nb::arg("path"), nb::arg("vertices"), nb::arg("triangles"), nb::arg("normals"),
      "Writes a mesh (float32 Nx3 vertices [m], int32 Mx3 triangles, float32 Nx3 normals) as "
      "binary PLY; returns the triangle count; OSError naming the file where it cannot be written");
  const DepthCodec::Params defaults;
  nb::class_<PyDepthCodec>(m, "DepthCodec",
                           "Lossless depth codec (RVL family, docs/wire.md); keeps its buffers.")
      .def(nb::init<int, int, int, int>(), nb::arg("encoding") = static_cast<int>(defaults.encoding),
           nb::arg("zstd_level") = defaults.zstd_level,
           nb::arg("max_width_px") = defaults.max_width_px,
           nb::arg("max_height_px") = defaults.max_height_px)
      .def("encode", &PyDepthCodec::encode, nb::arg("depth").noconvert(),
           "uint16 (height, width) C-contiguous array -> payload bytes")
      .def("decode", &PyDepthCodec::decode, nb::arg("payload"), nb::arg("encoding"),
           nb::arg("width"), nb::arg("height"),
           "payload bytes -> uint16 (height, width) array; ValueError naming what is malformed");

  nb::class_<PyMapSnapshot>(m, "MapSnapshot", "A map to mesh beside the fusion (Fusion.snapshot()).")
      .def("mesh", [](nb::handle self) { return nb::cast<PyMapSnapshot&>(self).mesh(self); },
           "Marching cubes: (vertices float32 Nx3 [m], triangles int32 Mx3, normals float32 Nx3), "
           "views that keep the snapshot alive")
      .def_prop_ro("num_blocks", &PyMapSnapshot::numBlocks)
      .def_prop_ro("update", &PyMapSnapshot::update,
                   "How mesh() brought the kept mesh up to date: map_blocks, blocks_changed, "
                   "blocks_remeshed, blocks_kept, collect_ms, mesh_ms; None before");

  nb::class_<RefineResult>(m, "RefineResult", "What refining one keyframe gave (FrameResult).")
      .def_ro("status", &RefineResult::status, "the engine's TrackingStatus")
      .def_prop_ro("T_world_cam", [](const RefineResult& r) { return matrixOf(r.T_world_cam); },
                   nb::rv_policy::move,
                   "4x4 camera-to-world; the last fused pose when lost")
      .def_ro("inlier_fraction", &RefineResult::inlier_fraction)
      .def_ro("rmse_m", &RefineResult::rmse_m)
      .def_ro("valid_depth_fraction", &RefineResult::valid_depth_fraction)
      .def_ro("lost_reason", &RefineResult::lost_reason)
      .def_ro("preprocess_ms", &RefineResult::preprocess_ms)
      .def_ro("track_ms", &RefineResult::track_ms)
      .def_ro("integrate_ms", &RefineResult::integrate_ms)
      .def_ro("raycast_ms", &RefineResult::raycast_ms)
      .def_ro("total_ms", &RefineResult::total_ms);

  bindParams(m);
  nb::class_<PyFusion>(m, "Fusion",
                       "A full-resolution map (hashed TSDF volume) of one vehicle and the pipeline "
                       "that refines keyframes against it and fuses them.")
      .def(nb::init<const kinfly::PinholeCamera&, const kinfly::HashedVolume::Params&,
                    const kinfly::FusionPipeline::Params&, int>(),
           nb::arg("camera"), nb::arg("volume"), nb::arg("pipeline"), nb::kw_only(),
           nb::arg("threads") = 2,
           "ValueError naming the field when the camera or a parameter is out of its range")
      // noconvert: a float or strided array is refused, not silently cast or copied.
      .def("refine", &PyFusion::refine, nb::arg("depth").noconvert(), nb::arg("utime"),
           nb::arg("T_world_cam_guess"),
           "Tracks a uint16 depth image frame-to-model from a guessed 4x4 pose, then fuses it")
      .def("fuse_at", &PyFusion::fuseAt, nb::arg("depth").noconvert(), nb::arg("utime"),
           nb::arg("T_world_cam"),
           "Fuses a uint16 depth image at a given 4x4 pose, without tracking (a keyframe already "
           "registered elsewhere)")
      .def("render", &PyFusion::render, nb::arg("full") = false,
           "The map shaded from the last fused pose (uint8): full=True raycasts every pixel, "
           "otherwise only where the last keyframe measured depth (no extra raycast)")
      .def("snapshot", &PyFusion::snapshot, nb::rv_policy::take_ownership,
           "The map to mesh while fusion goes on: copies the blocks changed since the last "
           "snapshot; meshing re-meshes only those and their neighbours")
      .def_prop_ro("num_blocks", &PyFusion::numBlocks)
      .def_prop_ro("memory_bytes", &PyFusion::memoryBytes)
      .def_prop_ro("voxel_size_m", &PyFusion::voxelSizeM);
}
