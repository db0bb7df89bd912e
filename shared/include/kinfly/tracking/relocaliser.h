// Relocalisation against keyframes coded by random ferns on depth (Glocker, Shotton, Criminisi
// and Izadi, "Real-time RGB-D camera relocalization via randomized ferns for keyframe encoding",
// TVCG 2015; InfiniTAM's relocaliser). A frame's code is the outcome of a fixed, seeded set of
// depth comparisons; a tracked frame whose code differs enough from every kept keyframe's
// becomes a keyframe, with its pose; a lost frame's code finds the keyframes that looked most
// like it, and their poses are where tracking tries again.
#pragma once

#include <array>
#include <cstdint>
#include <vector>

#include "kinfly/core/image.h"
#include "kinfly/core/se3.h"
#include "kinfly/core/status.h"

namespace kinfly {

class Relocaliser {
 public:
  struct Params {
    int ferns = 500;  // [1, 4096]: each fern is 4 comparisons, a code of 4 bits
    // Keyframes kept, their codes and poses allocated at construction; when full, no more are
    // added (a drone's flight in one room takes a few hundred).
    int max_keyframes = 1000;  // [1, 100000]
    // A tracked frame becomes a keyframe when its code differs from every kept keyframe's in at
    // least this share of the ferns (Glocker et al.'s 0.2: new enough to be worth keeping).
    float new_keyframe_dissimilarity = 0.2f;  // (0, 1]
    // Only keyframes whose code differs from the lost frame's in less than this share are tried:
    // beyond it the views have little in common and ICP from there would not converge.
    float max_candidate_dissimilarity = 0.5f;  // (0, 1]
    // The comparisons' depth thresholds are drawn between these, the sensor's range.
    float min_depth_m = 0.3f;  // [m] >= 0
    float max_depth_m = 4.0f;  // [m] > min_depth_m
    uint32_t seed = 1;         // the ferns' draw
    Status validate() const;
  };

  struct Candidate {
    Pose T_world_cam = Pose::Identity();
    float dissimilarity = 1.f;  // share of the ferns whose codes differ
  };

  explicit Relocaliser(const Params& params);
  const Params& params() const { return params_; }

  // Codes a depth image (metres; 0 or NaN where nothing was measured) into the relocaliser's
  // code buffer, which harvest() and nearest() then read. Any resolution: the comparisons are
  // placed relative to the image.
  void encode(ImageView<const float> depth_m);
  // Keeps the coded frame as a keyframe at T_world_cam when it differs enough from every kept
  // one and there is room; true if it did.
  bool harvest(const Pose& T_world_cam);
  // Up to `count` kept keyframes most like the coded frame, most alike first, each within
  // max_candidate_dissimilarity; returns how many were written to `out`.
  int nearest(int count, Candidate* out) const;
  int keyframes() const { return static_cast<int>(poses_.size()); }
  // Forgets every keyframe (their map is gone); the room reserved for them stays.
  void clear();

 private:
  struct Comparison {
    float u, v;         // [0, 1): where in the image, relative to its size
    float threshold_m;  // the bit is set where the depth is valid and beyond this
  };
  // Share of the ferns whose codes differ between the coded frame and keyframe k.
  float dissimilarity(int k) const;

  Params params_;
  std::vector<std::array<Comparison, 4>> ferns_;
  std::vector<uint8_t> code_;   // the coded frame, one code per fern
  std::vector<uint8_t> codes_;  // keyframes x ferns
  std::vector<Pose> poses_;
};

}  // namespace kinfly
