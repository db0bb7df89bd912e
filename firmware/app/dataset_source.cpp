#include <cmath>
#include <vector>

#include "depth_source.h"
#include "kinfly/io/png_io.h"
#include "kinfly/io/tum_dataset.h"

namespace kinfly::fw {
namespace {

class DatasetSource : public DepthSource {
 public:
  DatasetSource(std::vector<TumDepthEntry> entries, PinholeCamera camera, double depth_scale_m,
                std::string dir)
      : entries_(std::move(entries)), camera_(camera), depth_scale_m_(depth_scale_m),
        dir_(std::move(dir)) {}

  const PinholeCamera& camera() const override { return camera_; }
  double depthScaleM() const override { return depth_scale_m_; }
  std::string describe() const override {
    return "TUM folder " + dir_ + " (" + std::to_string(entries_.size()) + " frames)";
  }

  SourceStatus next(DepthCapture* out, std::string* why) override {
    if (next_ >= entries_.size()) return SourceStatus::kEnd;
    const TumDepthEntry& entry = entries_[next_++];
    if (std::string problem = loadDepthPng(entry.path, &out->depth); !problem.empty()) {
      *why = problem;
      return SourceStatus::kSkipped;
    }
    if (out->depth.width() != camera_.width || out->depth.height() != camera_.height) {
      *why = entry.path + ": " + std::to_string(out->depth.width()) + "x" +
             std::to_string(out->depth.height()) + " differs from the first frame's size";
      return SourceStatus::kSkipped;
    }
    out->utime = std::llround(entry.timestamp_s * 1e6);
    return SourceStatus::kFrame;
  }

 private:
  std::vector<TumDepthEntry> entries_;
  PinholeCamera camera_;
  double depth_scale_m_;
  std::string dir_;
  size_t next_ = 0;
};

}  // namespace

std::unique_ptr<DepthSource> openDatasetSource(const DatasetSourceParams& params,
                                               std::string* why) {
  std::vector<TumDepthEntry> entries;
  if (*why = readTumDepthList(params.tum_dir, &entries); !why->empty()) return nullptr;
  if (entries.empty()) {
    *why = params.tum_dir + "/depth.txt lists no frames";
    return nullptr;
  }
  PinholeCamera camera;
  if (!params.intrinsics.empty() && !parseIntrinsics(params.intrinsics, &camera, why))
    return nullptr;
  Image<uint16_t> first;
  if (*why = loadDepthPng(entries.front().path, &first); !why->empty()) return nullptr;
  camera.width = first.width();
  camera.height = first.height();
  if (*why = camera.validate(); !why->empty()) return nullptr;
  if (!(params.depth_units_per_m > 0.0)) {
    *why = "source.depth_units_per_m must be positive";
    return nullptr;
  }
  return std::make_unique<DatasetSource>(std::move(entries), camera,
                                         1.0 / params.depth_units_per_m, params.tum_dir);
}

}  // namespace kinfly::fw
