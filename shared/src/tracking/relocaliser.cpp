#include "kinfly/tracking/relocaliser.h"

#include <algorithm>
#include <random>
#include <sstream>

namespace kinfly {

Status Relocaliser::Params::validate() const {
  std::ostringstream why;
  if (ferns < 1 || ferns > 4096) why << "ferns must be in [1, 4096]; ";
  if (max_keyframes < 1 || max_keyframes > 100000) why << "max_keyframes must be in [1, 100000]; ";
  if (!(new_keyframe_dissimilarity > 0.f && new_keyframe_dissimilarity <= 1.f))
    why << "new_keyframe_dissimilarity must be in (0, 1]; ";
  if (!(max_candidate_dissimilarity > 0.f && max_candidate_dissimilarity <= 1.f))
    why << "max_candidate_dissimilarity must be in (0, 1]; ";
  if (!(min_depth_m >= 0.f)) why << "min_depth_m must be >= 0; ";
  if (!(max_depth_m > min_depth_m)) why << "max_depth_m must be > min_depth_m; ";
  return why.str().empty() ? Status() : Status::error(why.str());
}

Relocaliser::Relocaliser(const Params& params)
    : params_(params), ferns_(static_cast<size_t>(std::max(params.ferns, 1))),
      code_(ferns_.size()) {
  std::mt19937 rng(params_.seed);
  std::uniform_real_distribution<float> where(0.f, 1.f);
  std::uniform_real_distribution<float> depth(params_.min_depth_m, params_.max_depth_m);
  for (auto& fern : ferns_)
    for (Comparison& c : fern) c = {where(rng), where(rng), depth(rng)};
  const size_t keyframes = static_cast<size_t>(std::max(params_.max_keyframes, 1));
  codes_.reserve(keyframes * ferns_.size());
  poses_.reserve(keyframes);
}

void Relocaliser::encode(ImageView<const float> depth_m) {
  const int w = depth_m.width(), h = depth_m.height();
  for (size_t f = 0; f < ferns_.size(); ++f) {
    uint8_t code = 0;
    for (int i = 0; i < 4; ++i) {
      const Comparison& c = ferns_[f][i];
      const int x = std::min(static_cast<int>(c.u * static_cast<float>(w)), w - 1);
      const int y = std::min(static_cast<int>(c.v * static_cast<float>(h)), h - 1);
      const float z = depth_m(x, y);
      // NaN compares false: an unmeasured pixel reads as near.
      code = static_cast<uint8_t>(code | ((z > c.threshold_m ? 1 : 0) << i));
    }
    code_[f] = code;
  }
}

float Relocaliser::dissimilarity(int k) const {
  const uint8_t* kept = codes_.data() + static_cast<size_t>(k) * code_.size();
  int differ = 0;
  for (size_t f = 0; f < code_.size(); ++f) differ += kept[f] != code_[f];
  return static_cast<float>(differ) / static_cast<float>(code_.size());
}

bool Relocaliser::harvest(const Pose& T_world_cam) {
  if (keyframes() >= params_.max_keyframes) return false;
  for (int k = 0; k < keyframes(); ++k)
    if (dissimilarity(k) < params_.new_keyframe_dissimilarity) return false;
  codes_.insert(codes_.end(), code_.begin(), code_.end());
  poses_.push_back(T_world_cam);
  return true;
}

void Relocaliser::clear() {
  codes_.clear();
  poses_.clear();
}

int Relocaliser::nearest(int count, Candidate* out) const {
  int found = 0;
  for (int k = 0; k < keyframes(); ++k) {
    const float d = dissimilarity(k);
    if (!(d < params_.max_candidate_dissimilarity)) continue;
    // Insertion into the short sorted list: `count` is a handful.
    int at = std::min(found, count);
    while (at > 0 && out[at - 1].dissimilarity > d) --at;
    if (at >= count) continue;
    for (int i = std::min(found, count - 1); i > at; --i) out[i] = out[i - 1];
    out[at] = {poses_[static_cast<size_t>(k)], d};
    found = std::min(found + 1, count);
  }
  return found;
}

}  // namespace kinfly
