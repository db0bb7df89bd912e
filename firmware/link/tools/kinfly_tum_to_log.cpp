// kinfly-tum-to-log: converts a TUM RGB-D folder into an LCM event log (lcm-logger's format), so
// that recorded datasets replay exactly like recorded flights. Every depth frame becomes a
// depth_keyframe_t on KINFLY_<vid>_DEPTH at its capture time; groundtruth.txt, when present,
// becomes ground_truth_t messages on KINFLY_<vid>_GROUND_TRUTH.
#include <CLI/CLI.hpp>
#include <lcm/lcm-cpp.hpp>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <string>
#include <vector>

#include "kinfly/codec/depth_codec.h"
#include "kinfly/link/channels.h"
#include "kinfly/link/conversions.h"
#include "kinfly/odometry_t.hpp"
#include "kinfly/ground_truth_t.hpp"
#include "kinfly/io/png_io.h"
#include "kinfly/io/tum_dataset.h"

namespace {

using namespace kinfly;

// Ground truth this far outside the depth frames' time span is left out: it belongs to no frame.
constexpr double kGroundTruthMarginS = 1.0;

int fail(const std::string& message) {
  std::cerr << "kinfly-tum-to-log: error: " << message << "\n";
  return 1;
}

int64_t toUtime(double timestamp_s) { return std::llround(timestamp_s * 1e6); }

template <class T>
void writeEvent(lcm::LogFile* log, const std::string& channel, int64_t utime, const T& message,
                std::vector<uint8_t>* buffer) {
  buffer->resize(static_cast<size_t>(message.getEncodedSize()));
  message.encode(buffer->data(), 0, static_cast<int>(buffer->size()));
  lcm::LogEvent event;
  event.timestamp = utime;
  event.channel = channel;
  event.datalen = static_cast<int32_t>(buffer->size());
  event.data = buffer->data();
  log->writeEvent(&event);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Convert a TUM RGB-D folder (depth.txt + depth/*.png, optional groundtruth.txt) into an LCM "
      "event log that kinfly replays like a recorded flight."};
  std::string tum_dir, out_path, intrinsics, encoding_name = "palette_rvl_zstd";
  int vehicle_id = 1, max_frames = 0;
  double depth_scale = 5000.0;
  bool force = false;
  app.add_option("--tum", tum_dir, "TUM RGB-D folder")->required()->check(CLI::ExistingDirectory);
  app.add_option("--out", out_path, "LCM log to write")->required();
  app.add_option("--vehicle", vehicle_id, "vehicle id in the channel names and messages")
      ->check(CLI::Range(0, link::kMaxVehicleId))
      ->capture_default_str();
  app.add_option("--intrinsics", intrinsics, "fx,fy,cx,cy in pixels (default: TUM freiburg3)");
  app.add_option("--depth-scale", depth_scale, "raw depth units per metre (TUM: 5000)")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app.add_option("--encoding", encoding_name, "raw16, rvl, rvl_zstd or palette_rvl_zstd")
      ->capture_default_str();
  app.add_option("--max-frames", max_frames, "convert only the first N frames (0: all)")
      ->check(CLI::NonNegativeNumber);
  app.add_flag("--force", force, "replace an existing log");
  CLI11_PARSE(app, argc, argv);

  DepthCodec::Params codec_params;
  if (!parseDepthEncoding(encoding_name, &codec_params.encoding))
    return fail("--encoding: unknown encoding \"" + encoding_name + "\"");
  PinholeCamera camera;
  if (!intrinsics.empty())
    if (const Status parsed = parseIntrinsics(intrinsics, &camera); !parsed.ok())
      return fail(parsed.message());
  if (!force && std::filesystem::exists(out_path))
    return fail(out_path + " already exists (pass --force to replace it)");

  std::vector<TumDepthEntry> frames;
  if (const Status read = readTumDepthList(tum_dir, &frames); !read.ok())
    return fail(read.message());
  if (max_frames > 0 && static_cast<size_t>(max_frames) < frames.size())
    frames.resize(static_cast<size_t>(max_frames));
  if (frames.empty()) return fail(tum_dir + "/depth.txt lists no frames");

  std::vector<StampedPose> truth;
  const std::string truth_path = tum_dir + "/groundtruth.txt";
  if (std::filesystem::exists(truth_path)) {
    if (const Status read = readTumTrajectory(truth_path, &truth); !read.ok())
      return fail(read.message());
  }
  const double first_s = frames.front().timestamp_s - kGroundTruthMarginS;
  const double last_s = frames.back().timestamp_s + kGroundTruthMarginS;

  // Written beside the target and renamed when complete: an interrupted run leaves no
  // half-written log under the requested name.
  const std::string partial = out_path + ".partial";
  int64_t truth_written = 0;
  {
    lcm::LogFile log(partial, "w");
    if (!log.good()) return fail("cannot write " + partial);
    DepthCodec codec(codec_params);
    Image<uint16_t> raw;
    depth_keyframe_t message;
    std::vector<uint8_t> buffer;
    const std::string depth_channel = link::channelName(link::Channel::kDepth, vehicle_id);
    const std::string truth_channel = link::channelName(link::Channel::kGroundTruth, vehicle_id);
    size_t next_truth = 0;
    const auto writeTruthUntil = [&](double until_s) {
      for (; next_truth < truth.size() && truth[next_truth].timestamp_s <= until_s; ++next_truth) {
        const StampedPose& p = truth[next_truth];
        if (p.timestamp_s < first_s || p.timestamp_s > last_s) continue;
        ground_truth_t pose;
        pose.vehicle_id = vehicle_id;
        link::fillGroundTruth(toUtime(p.timestamp_s), p.T_world_cam, &pose);
        writeEvent(&log, truth_channel, pose.utime, pose, &buffer);
        ++truth_written;
      }
    };
    for (size_t i = 0; i < frames.size(); ++i) {
      if (const Status loaded = loadDepthPng(frames[i].path, &raw); !loaded.ok())
        return fail(loaded.message());
      camera.width = raw.width();
      camera.height = raw.height();
      if (const Status valid = camera.validate(); !valid.ok())
        return fail(frames[i].path + ": " + valid.message());
      writeTruthUntil(frames[i].timestamp_s);
      message.vehicle_id = vehicle_id;
      link::KeyframeHeader header;  // a raw capture: not a keyframe, no pose
      header.utime = toUtime(frames[i].timestamp_s);
      header.frame_id = static_cast<int64_t>(i);
      header.keyframe_id = -1;
      link::fillKeyframe(header, &message);
      const CodecResult encoded =
          link::encodeDepth(codec, raw, camera, 1.0 / depth_scale, &message);
      if (!encoded.ok())
        return fail(frames[i].path + ": cannot encode: " + toString(encoded.status));
      writeEvent(&log, depth_channel, message.utime, message, &buffer);
      if ((i + 1) % 50 == 0 || i + 1 == frames.size())
        std::fprintf(stderr, "\rkinfly-tum-to-log: %zu/%zu frames", i + 1, frames.size());
    }
    writeTruthUntil(last_s);
    std::fputc('\n', stderr);
  }
  std::error_code error;
  std::filesystem::rename(partial, out_path, error);
  if (error) return fail("cannot rename " + partial + " to " + out_path + ": " + error.message());
  std::printf("wrote %s: %zu depth frames (%s), %lld ground-truth poses, vehicle %d\n",
              out_path.c_str(), frames.size(), encoding_name.c_str(),
              static_cast<long long>(truth_written), vehicle_id);
  return 0;
}
