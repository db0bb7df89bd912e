// kinfly-mesh-bench: incremental meshing (IncrementalMesher) against a full re-mesh
// (MarchingCubes::extract) on the TUM sequence, on its map and on a map ten times larger.
//
// Maps, fused at the ground's settings (1 cm voxels, 4 cm truncation, full resolution) at the
// motion-capture poses:
//   tum200     the sequence forwards: the map of one flight;
//   tum200_x10 the sequence ten times, forwards and backwards alternately, each pass shifted
//              20 m along x (beyond the 4 m depth range): ten such maps side by side.
// Then the sequence flies once more over the last copy (backwards if the last pass went
// forwards) and the meshers update every 1, 5 and 25 frames, each on its own (several meshers
// can watch one volume: each keeps its own stamps), on one thread as the station's mesher does;
// a full re-mesh of the same volume is timed every 25 frames. Prints JSON; never fails on
// timings (exit 1 only for unreadable input).
#include <CLI/CLI.hpp>
#include <omp.h>

#include <chrono>
#include <cstdio>
#include <string>
#include <vector>

#include "kinfly/pipeline/fusion_pipeline.h"
#include "kinfly/mesh/incremental_mesher.h"
#include "kinfly/mesh/marching_cubes.h"
#include "kinfly/io/png_io.h"
#include "kinfly/volume/tsdf_volume.h"
#include "kinfly/io/tum_dataset.h"
#include "percentile.h"

namespace {

using kinfly::tools::percentile;
using Clock = std::chrono::steady_clock;

constexpr double kTumDepthScale = 1.0 / 5000.0;  // [m per unit]
constexpr double kPoseMaxDtS = 0.02;             // [s] depth to motion capture association
constexpr double kCopyShiftM = 20.0;             // [m] between copies: beyond the 4 m range
constexpr int kFullEveryFrames = 25;

double msSince(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

struct Frame {
  kinfly::Image<uint16_t> depth;
  int64_t utime = 0;
  kinfly::Pose T_world_cam = kinfly::Pose::Identity();
};

struct Series {
  int interval_frames = 0;
  std::unique_ptr<kinfly::IncrementalMesher> mesher;
  std::vector<double> changed, remeshed, update_ms, collect_ms, us_per_block;
};

struct MapRun {
  std::string name;
  int copies = 0;
  size_t map_blocks_before = 0, map_blocks_after = 0;
  double initial_mesh_ms = 0;
  std::vector<double> full_ms, full_blocks;
  std::vector<Series> series;
  bool equal_to_full = false;
  double fuse_s = 0;
};

void printStats(const char* name, const std::vector<double>& v, const char* tail) {
  std::printf("\"%s\": {\"median\": %.3f, \"p90\": %.3f, \"max\": %.3f}%s", name,
              percentile(v, 0.5), percentile(v, 0.9), percentile(v, 1.0), tail);
}

MapRun runMap(const std::string& name, int copies, const std::vector<Frame>& frames,
              const std::vector<int>& intervals) {
  MapRun run;
  run.name = name;
  run.copies = copies;
  kinfly::HashedVolume::Params volume_params;
  volume_params.voxel_size_m = 0.01f;
  kinfly::HashedVolume volume(volume_params);
  kinfly::FusionPipeline::Params params;
  params.preprocess.depth_scale_m = kTumDepthScale;
  params.integrate.truncation_m = 4.f * volume_params.voxel_size_m;
  kinfly::FusionPipeline pipeline(kinfly::PinholeCamera(), params, &volume);
  for (int interval : intervals) {
    Series s;
    s.interval_frames = interval;
    s.mesher = std::make_unique<kinfly::IncrementalMesher>(kinfly::IncrementalMesher::Params());
    run.series.push_back(std::move(s));
  }
  const kinfly::MarchingCubes full(kinfly::MarchingCubes::Params{});

  const auto fuse_start = Clock::now();
  const int n = static_cast<int>(frames.size());
  for (int pass = 0; pass <= copies; ++pass) {
    const bool measured = pass == copies;  // the extra flight over the last copy
    const int copy = measured ? copies - 1 : pass;
    const bool forwards = pass % 2 == 0;
    kinfly::Pose shift = kinfly::Pose::Identity();
    shift.translation().x() = kCopyShiftM * copy;
    if (measured) {
      run.fuse_s = std::chrono::duration<double>(Clock::now() - fuse_start).count();
      run.map_blocks_before = volume.numAllocatedBlocks();
      for (Series& s : run.series) {
        const auto t0 = Clock::now();
        s.mesher->update(volume, /*parallel=*/false);
        run.initial_mesh_ms = msSince(t0);
      }
    }
    for (int k = 0; k < n; ++k) {
      const Frame& f = frames[static_cast<size_t>(forwards ? k : n - 1 - k)];
      pipeline.processFrameAtPose(f.depth.view(), f.utime, shift * f.T_world_cam);
      if (!measured) continue;
      for (Series& s : run.series) {
        if ((k + 1) % s.interval_frames != 0) continue;
        const kinfly::MeshUpdateResult r = s.mesher->update(volume, /*parallel=*/false);
        s.changed.push_back(r.blocks_changed);
        s.remeshed.push_back(r.blocks_remeshed);
        s.update_ms.push_back(r.total_ms());
        s.collect_ms.push_back(r.collect_ms);
        if (r.blocks_remeshed > 0) s.us_per_block.push_back(1e3 * r.mesh_ms / r.blocks_remeshed);
      }
      if ((k + 1) % kFullEveryFrames == 0) {
        const auto t0 = Clock::now();
        const kinfly::TriangleMesh mesh = full.extract(volume);
        run.full_ms.push_back(msSince(t0));
        run.full_blocks.push_back(static_cast<double>(volume.numAllocatedBlocks()));
      }
    }
  }
  run.map_blocks_after = volume.numAllocatedBlocks();
  // The kept mesh is the full one: same vertices and triangles, in the same order.
  Series& last = run.series.front();
  last.mesher->update(volume, false);
  const kinfly::TriangleMesh a = last.mesher->mesh(), b = full.extract(volume);
  run.equal_to_full = a.vertices == b.vertices && a.triangles == b.triangles && a.normals == b.normals;
  return run;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Incremental meshing against a full re-mesh on the TUM sequence (JSON on stdout)"};
  std::string tum_dir;
  int copies = 10;
  int threads = 2;
  app.add_option("--tum", tum_dir, "TUM folder (depth.txt, groundtruth.txt)")->required();
  app.add_option("--copies", copies, "copies of the map in the large map")->check(CLI::Range(2, 50));
  app.add_option("--threads", threads, "fusion threads (meshing runs on one)")->check(CLI::Range(1, 64));
  CLI11_PARSE(app, argc, argv);
  omp_set_num_threads(threads);

  std::vector<kinfly::TumDepthEntry> entries;
  std::vector<kinfly::StampedPose> truth;
  kinfly::Status read = kinfly::readTumDepthList(tum_dir, &entries);
  if (read.ok()) read = kinfly::readTumTrajectory(tum_dir + "/groundtruth.txt", &truth);
  if (!read.ok()) {
    std::fprintf(stderr, "kinfly-mesh-bench: %s\n", read.message().c_str());
    return 1;
  }
  std::vector<Frame> frames;
  for (const kinfly::TumDepthEntry& e : entries) {
    const kinfly::StampedPose* pose = kinfly::findNearestPose(truth, e.timestamp_s, kPoseMaxDtS);
    if (pose == nullptr) continue;
    Frame f;
    if (const kinfly::Status loaded = kinfly::loadDepthPng(e.path, &f.depth); !loaded.ok()) {
      std::fprintf(stderr, "kinfly-mesh-bench: %s\n", loaded.message().c_str());
      return 1;
    }
    f.utime = static_cast<int64_t>(e.timestamp_s * 1e6);
    f.T_world_cam = pose->T_world_cam;
    frames.push_back(std::move(f));
  }

  const std::vector<int> intervals = {1, 5, 25};
  std::vector<MapRun> runs;
  runs.push_back(runMap("tum200", 1, frames, intervals));
  runs.push_back(runMap("tum200_x" + std::to_string(copies), copies, frames, intervals));

  std::printf("{\"dataset\": \"%s\", \"frames\": %zu, \"voxel_size_m\": 0.01, "
              "\"fusion_threads\": %d, \"mesh_threads\": 1, \"maps\": [\n",
              tum_dir.c_str(), frames.size(), threads);
  for (size_t m = 0; m < runs.size(); ++m) {
    const MapRun& r = runs[m];
    std::printf(" {\"map\": \"%s\", \"copies\": %d, \"fuse_s\": %.1f, \"map_blocks\": %zu, "
                "\"map_blocks_after_measured_flight\": %zu, \"initial_mesh_ms\": %.1f, "
                "\"incremental_equals_full\": %s,\n  ",
                r.name.c_str(), r.copies, r.fuse_s, r.map_blocks_before, r.map_blocks_after,
                r.initial_mesh_ms, r.equal_to_full ? "true" : "false");
    printStats("full_remesh_ms", r.full_ms, ", ");
    std::printf("\"full_remesh_blocks\": %.0f,\n  \"updates\": [\n", percentile(r.full_blocks, 0.5));
    const double full_median = percentile(r.full_ms, 0.5);
    for (size_t i = 0; i < r.series.size(); ++i) {
      const Series& s = r.series[i];
      std::printf("   {\"every_frames\": %d, \"updates\": %zu, ", s.interval_frames, s.update_ms.size());
      printStats("blocks_changed", s.changed, ", ");
      printStats("blocks_remeshed", s.remeshed, ", ");
      printStats("update_ms", s.update_ms, ", ");
      printStats("collect_ms", s.collect_ms, ", ");
      printStats("mesh_us_per_remeshed_block", s.us_per_block, ", ");
      const double median = percentile(s.update_ms, 0.5);
      std::printf("\"full_over_update\": %.1f}%s\n", median > 0 ? full_median / median : 0.0,
                  i + 1 < r.series.size() ? "," : "");
    }
    std::printf("  ]}%s\n", m + 1 < runs.size() ? "," : "");
  }
  std::printf("]}\n");
  return 0;
}
