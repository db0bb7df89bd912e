#include <cmath>
#include <vector>

#include "kinfly/sources/dataset_source.h"

#include "kinfly/core/range_check.h"
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
    if (Status loaded = loadDepthPng(entry.path, &out->depth); !loaded.ok()) {
      *why = loaded.message();
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

Status DatasetSourceParams::validate() const {
  return outOfRange("source.depth_scale_m", depth_scale_m, 1e-6, 1.0);
}

StatusOr<std::unique_ptr<DepthSource>> openDatasetSource(const DatasetSourceParams& params) {
  if (Status valid = params.validate(); !valid.ok()) return valid;
  std::vector<TumDepthEntry> entries;
  if (Status read = readTumDepthList(params.tum_dir, &entries); !read.ok()) return read;
  if (entries.empty()) return Status::error(params.tum_dir + "/depth.txt lists no frames");
  PinholeCamera camera;
  if (!params.intrinsics.empty())
    if (Status parsed = parseIntrinsics(params.intrinsics, &camera); !parsed.ok()) return parsed;
  Image<uint16_t> first;
  if (Status loaded = loadDepthPng(entries.front().path, &first); !loaded.ok()) return loaded;
  camera.width = first.width();
  camera.height = first.height();
  if (Status valid = camera.validate(); !valid.ok()) return valid;
  return std::make_unique<DatasetSource>(std::move(entries), camera, params.depth_scale_m,
                                         params.tum_dir);
}

}  // namespace kinfly::fw
