// kinfly-fuse: offline KinectFusion over a recorded TUM RGB-D sequence. Writes the camera
// trajectory, a mesh of the fused map and per-stage timing statistics.
#include <CLI/CLI.hpp>
#include <omp.h>
#include <sys/resource.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <numeric>
#include <cstdio>
#include <ctime>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include "kinfly/core/json.h"
#include "kinfly/io/png_io.h"
#include "kinfly/io/tum_dataset.h"
#include "kinfly/mesh/marching_cubes.h"
#include "kinfly/mesh/mesh.h"
#include "kinfly/pipeline/fusion_pipeline.h"
#include "kinfly/volume/tsdf_volume.h"
#include "percentile.h"

namespace {

using kinfly::FrameResult;
using kinfly::jsonEscape;
using kinfly::tools::percentile;
using kinfly::TrackingStatus;

struct Options {
  std::string tum_dir, out_dir, intrinsics, poses_path;
  std::string volume = "hashed";
  double depth_scale = 5000.0;
  float voxel_size_m = 0.f;   // 0: per-volume default
  float truncation_m = 0.f;   // 0: from the voxel size
  int threads = 2;
  int max_frames = 0;
  int downsample = 1;
  int icp_fine_iterations = kinfly::IcpTracker::Params().iterations_coarse_to_fine.back();
  int model_level = kinfly::FusionPipeline::Params().model_level;
  double pose_max_dt_s = 0.02;
  bool verbose = false;
};

int fail(const std::string& message) {
  std::cerr << "kinfly-fuse: error: " << message << "\n";
  return 1;
}

double threadCpuMs() {
  timespec t{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return 1e3 * static_cast<double>(t.tv_sec) + 1e-6 * static_cast<double>(t.tv_nsec);
}

double peakRssMb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return static_cast<double>(usage.ru_maxrss) / 1024.0;  // Linux reports KiB
}

}  // namespace

int main(int argc, char** argv) {
  Options opt;
  CLI::App app{
      "kinfly-fuse: offline KinectFusion over a recorded TUM RGB-D sequence.\n"
      "Tracks every depth frame against the fused model (or uses --poses), fuses it into a TSDF\n"
      "volume and writes OUTDIR/trajectory.tum (camera-to-world, first frame at identity),\n"
      "OUTDIR/mesh.ply, OUTDIR/render.png and OUTDIR/stats.json."};
  app.add_option("--tum", opt.tum_dir, "TUM RGB-D folder holding depth.txt and depth/*.png (16-bit)")->required();
  app.add_option("--out", opt.out_dir, "output folder (created if missing)")->required();
  app.add_option("--intrinsics", opt.intrinsics,
                 "fx,fy,cx,cy in pixels of the input images (default: TUM freiburg3 535.4,539.2,320.1,247.6)");
  app.add_option("--depth-scale", opt.depth_scale, "raw depth units per metre: metres = value / S (TUM 5000, OpenNI 1000)")
      ->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--volume", opt.volume, "hashed: unbounded voxel-block hash (ground); dense: 128^3 grid that follows the camera (drone)")
      ->capture_default_str()->check(CLI::IsMember({"hashed", "dense"}));
  app.add_option("--voxel-size", opt.voxel_size_m, "voxel edge in metres (default 0.01 hashed, 0.03 dense)")
      ->check(CLI::PositiveNumber);
  app.add_option("--truncation", opt.truncation_m, "TSDF truncation in metres (default 4 voxels)")
      ->check(CLI::PositiveNumber);
  app.add_option("--threads", opt.threads, "worker threads for the stage loops")->capture_default_str()->check(CLI::Range(1, 256));
  app.add_option("--max-frames", opt.max_frames, "stop after this many frames (0: all)")->capture_default_str()->check(CLI::NonNegativeNumber);
  app.add_option("--poses", opt.poses_path, "map with these camera-to-world poses (TUM format, matched by timestamp) instead of tracking");
  app.add_option("--pose-max-dt", opt.pose_max_dt_s, "with --poses: largest time difference accepted when matching, seconds")
      ->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--downsample", opt.downsample, "run the whole pipeline at 1/N resolution (2: 320x240, as the drone does)")
      ->capture_default_str()->check(CLI::IsMember({1, 2, 4}));
  app.add_option("--icp-fine-iterations", opt.icp_fine_iterations,
                 "ICP iterations at the finest level (the drone's kinfly-fw runs 2: odometry.icp_fine_iterations)")
      ->capture_default_str()->check(CLI::Range(1, 20));
  app.add_option("--model-level", opt.model_level,
                 "raycast the model for tracking at this pyramid level's resolution (1: half; "
                 "kinfly-fw's odometry.model_level)")
      ->capture_default_str()->check(CLI::Range(0, kinfly::kPyramidLevels - 2));
  app.add_flag("--verbose", opt.verbose, "progress line for every frame (default: every 20th and every lost frame)");
  CLI11_PARSE(app, argc, argv);

  std::vector<kinfly::TumDepthEntry> entries;
  if (const kinfly::Status status = kinfly::readTumDepthList(opt.tum_dir, &entries); !status.ok()) return fail(status.message());
  if (opt.max_frames > 0 && static_cast<size_t>(opt.max_frames) < entries.size()) entries.resize(opt.max_frames);

  kinfly::Image<uint16_t> depth;
  if (const kinfly::Status status = kinfly::loadDepthPng(entries.front().path, &depth); !status.ok()) return fail(status.message());
  kinfly::PinholeCamera camera;
  if (!opt.intrinsics.empty())
    if (const kinfly::Status parsed = kinfly::parseIntrinsics(opt.intrinsics, &camera); !parsed.ok())
      return fail(parsed.message());
  camera.width = depth.width();
  camera.height = depth.height();
  if (const kinfly::Status status = camera.validate(); !status.ok()) return fail("--intrinsics: " + status.message());
  if (camera.width % opt.downsample != 0 || camera.height % opt.downsample != 0)
    return fail("--downsample " + std::to_string(opt.downsample) + " does not divide the image size");

  std::vector<kinfly::StampedPose> given_poses;
  if (!opt.poses_path.empty())
    if (const kinfly::Status status = kinfly::readTumTrajectory(opt.poses_path, &given_poses); !status.ok()) return fail(status.message());

  const bool dense = opt.volume == "dense";
  const float voxel_m = opt.voxel_size_m > 0.f ? opt.voxel_size_m : (dense ? 0.03f : 0.01f);
  std::unique_ptr<kinfly::TsdfVolume> volume;
  if (dense) {
    kinfly::DenseVolume::Params p;
    p.voxel_size_m = voxel_m;
    if (const kinfly::Status status = p.validate(); !status.ok()) return fail(status.message());
    volume = std::make_unique<kinfly::DenseVolume>(p);
  } else {
    kinfly::HashedVolume::Params p;
    p.voxel_size_m = voxel_m;
    if (const kinfly::Status status = p.validate(); !status.ok()) return fail(status.message());
    volume = std::make_unique<kinfly::HashedVolume>(p);
  }
  kinfly::FusionPipeline::Params params;
  params.preprocess.depth_scale_m = 1.0 / opt.depth_scale;
  params.preprocess.downsample = opt.downsample;
  params.icp.iterations_coarse_to_fine.back() = opt.icp_fine_iterations;
  params.model_level = opt.model_level;
  params.integrate.truncation_m = opt.truncation_m > 0.f ? opt.truncation_m : 4.f * voxel_m;
  if (const kinfly::Status status = params.validate(voxel_m); !status.ok()) return fail(status.message());

  std::error_code mkdir_error;
  std::filesystem::create_directories(opt.out_dir, mkdir_error);
  if (mkdir_error) return fail("cannot create " + opt.out_dir + ": " + mkdir_error.message());
  omp_set_num_threads(opt.threads);

  kinfly::FusionPipeline pipeline(camera, params, volume.get());
  std::vector<kinfly::StampedPose> trajectory;
  std::vector<double> frame_ms;
  // The calling thread's CPU time per frame: at --threads 1 the whole frame's work without the
  // time the scheduler gave to other processes, which a shared machine's wall clock includes.
  std::vector<double> frame_cpu_ms;
  std::map<std::string, std::vector<double>> stage_ms;
  std::map<std::string, int> status_counts = {{"first", 0}, {"ok", 0}, {"lost", 0}, {"given", 0}};
  std::vector<std::string> lost_notes;

  for (size_t i = 0; i < entries.size(); ++i) {
    const kinfly::TumDepthEntry& e = entries[i];
    if (const kinfly::Status status = kinfly::loadDepthPng(e.path, &depth); !status.ok()) return fail(status.message());
    if (depth.width() != camera.width || depth.height() != camera.height)
      return fail(e.path + ": image size " + std::to_string(depth.width()) + "x" + std::to_string(depth.height()) +
                  " differs from the first frame's");
    const int64_t utime = static_cast<int64_t>(std::llround(e.timestamp_s * 1e6));
    FrameResult r;
    const double cpu_before_ms = threadCpuMs();
    if (given_poses.empty()) {
      r = pipeline.processFrame(depth.view(), utime);
    } else if (const kinfly::StampedPose* p = kinfly::findNearestPose(given_poses, e.timestamp_s, opt.pose_max_dt_s)) {
      r = pipeline.processFrameAtPose(depth.view(), utime, p->T_world_cam);
    } else {
      r.utime = utime;
      r.T_world_cam = pipeline.pose();
      r.status = TrackingStatus::kLost;
      r.lost_reason = "no pose within " + std::to_string(opt.pose_max_dt_s) + " s in " + opt.poses_path;
    }
    const double cpu_ms = threadCpuMs() - cpu_before_ms;
    status_counts[kinfly::toString(r.status)]++;
    if (r.status == TrackingStatus::kLost)
      lost_notes.push_back("frame " + std::to_string(i) + " (" + e.path + "): " + r.lost_reason);
    trajectory.push_back({e.timestamp_s, r.T_world_cam});
    if (r.status != TrackingStatus::kLost) {
      frame_ms.push_back(r.ms.total);
      frame_cpu_ms.push_back(cpu_ms);
      stage_ms["preprocess"].push_back(r.ms.preprocess);
      stage_ms["track"].push_back(r.ms.track);
      stage_ms["integrate"].push_back(r.ms.integrate);
      stage_ms["raycast"].push_back(r.ms.raycast);
    }
    if (opt.verbose || (i + 1) % 20 == 0 || i + 1 == entries.size() || r.status == TrackingStatus::kLost) {
      std::fprintf(stderr, "[%4zu/%zu] %-5s %6.1f ms (pre %.1f track %.1f fuse %.1f ray %.1f)  inliers %3.0f%%  rmse %.1f mm  blocks %zu%s%s\n",
                   i + 1, entries.size(), kinfly::toString(r.status), r.ms.total, r.ms.preprocess, r.ms.track,
                   r.ms.integrate, r.ms.raycast, 100.0 * r.inlier_fraction, 1000.0 * r.rmse_m,
                   volume->numAllocatedBlocks(), r.lost_reason.empty() ? "" : "  ", r.lost_reason.c_str());
    }
  }

  const std::string traj_path = opt.out_dir + "/trajectory.tum";
  if (const kinfly::Status status = kinfly::writeTumTrajectory(traj_path, trajectory); !status.ok()) return fail(status.message());

  const std::string render_path = opt.out_dir + "/render.png";
  kinfly::Image<uint8_t> render(pipeline.camera().width, pipeline.camera().height, 0);
  pipeline.renderShaded(render.view());
  if (const kinfly::Status status = kinfly::writeGrayPng(render_path, render.view()); !status.ok())
    return fail(status.message());

  std::fprintf(stderr, "meshing %zu blocks...\n", volume->numAllocatedBlocks());
  const kinfly::TriangleMesh mesh = kinfly::MarchingCubes(kinfly::MarchingCubes::Params()).extract(*volume);
  const std::string mesh_path = opt.out_dir + "/mesh.ply";
  if (const kinfly::Status status = kinfly::writePly(mesh, mesh_path); !status.ok()) return fail(status.message());

  const std::string stats_path = opt.out_dir + "/stats.json";
  std::ofstream js(stats_path);
  js << "{\n  \"frames\": " << entries.size() << ",\n";
  js << "  \"width\": " << pipeline.camera().width << ", \"height\": " << pipeline.camera().height << ",\n";
  js << "  \"volume\": \"" << opt.volume << "\", \"voxel_size_m\": " << voxel_m
     << ", \"truncation_m\": " << params.integrate.truncation_m << ", \"threads\": " << opt.threads << ",\n";
  js << "  \"frame_ms\": {\"median\": " << percentile(frame_ms, 0.5) << ", \"p90\": " << percentile(frame_ms, 0.9)
     << ", \"p99\": " << percentile(frame_ms, 0.99)
     << ", \"mean\": " << (frame_ms.empty() ? 0.0 : std::accumulate(frame_ms.begin(), frame_ms.end(), 0.0) / static_cast<double>(frame_ms.size()))
     << "},\n  \"frame_cpu_ms\": {\"median\": " << percentile(frame_cpu_ms, 0.5)
     << ", \"p90\": " << percentile(frame_cpu_ms, 0.9) << ", \"p99\": " << percentile(frame_cpu_ms, 0.99)
     << "},\n  \"stage_ms\": {";
  bool first = true;
  for (const auto& [stage, values] : stage_ms) {
    js << (first ? "" : ", ") << "\"" << stage << "\": {\"median\": " << percentile(values, 0.5)
       << ", \"p90\": " << percentile(values, 0.9) << "}";
    first = false;
  }
  js << "},\n  \"tracking\": {";
  first = true;
  for (const auto& [status, count] : status_counts) {
    js << (first ? "" : ", ") << "\"" << status << "\": " << count;
    first = false;
  }
  js << "},\n  \"lost\": [";
  for (size_t i = 0; i < lost_notes.size(); ++i) js << (i ? ", " : "") << "\"" << jsonEscape(lost_notes[i]) << "\"";
  js << "],\n  \"peak_rss_mb\": " << peakRssMb() << ",\n  \"allocated_blocks\": " << volume->numAllocatedBlocks()
     << ",\n  \"volume_memory_mb\": " << static_cast<double>(volume->memoryBytes()) / (1024.0 * 1024.0)
     << ",\n  \"mesh_vertices\": " << mesh.vertices.size() << ", \"mesh_triangles\": " << mesh.triangles.size() << "\n}\n";
  js.close();
  if (!js) return fail("failed writing " + stats_path);

  std::fprintf(stderr, "done: %zu frames, median %.1f ms/frame (%d lost)\n  trajectory: %s\n  mesh:       %s\n  render:     %s\n  stats:      %s\n",
               entries.size(), percentile(frame_ms, 0.5), status_counts["lost"], traj_path.c_str(),
               mesh_path.c_str(), render_path.c_str(), stats_path.c_str());
  return 0;
}
