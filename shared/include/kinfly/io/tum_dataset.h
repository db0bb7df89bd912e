// TUM RGB-D folders and TUM trajectory files. Errors come back as a Status naming the file and
// line; nothing here throws.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "kinfly/core/se3.h"
#include "kinfly/core/status.h"

namespace kinfly {

struct TumDepthEntry {
  double timestamp_s = 0;
  std::string path;  // absolute or relative to the working directory
};

struct StampedPose {
  double timestamp_s = 0;
  Pose T_world_cam = Pose::Identity();
};

// Reads DIR/depth.txt ("timestamp filename" per line, '#' comments).
Status readTumDepthList(const std::string& dir, std::vector<TumDepthEntry>* entries);

// TUM trajectory: "t tx ty tz qx qy qz qw" per line, camera-to-world.
Status readTumTrajectory(const std::string& path, std::vector<StampedPose>* poses);
Status writeTumTrajectory(const std::string& path, const std::vector<StampedPose>& poses);

// The pose nearest in time to t within max_dt_s, or nullptr. `poses` sorted by time.
const StampedPose* findNearestPose(const std::vector<StampedPose>& poses, double t,
                                   double max_dt_s);

}  // namespace kinfly
