// How fuzz_depth_decode reads its input, shared with the corpus generator: three bytes standing
// for the keyframe message's fields, then the payload.
//   byte 0: encoding, any value (4..255 must be rejected as kBadEncoding)
//   byte 1: width in pixels, byte 2: height in pixels (0 and above kMaxSidePx must be rejected)
//   bytes 3..: the payload
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "kinfly/depth_codec.h"

namespace kinfly::fuzz {

constexpr size_t kHeaderBytes = 3;
// Small images keep each run fast, so the fuzzer spends its time on the payload's structure;
// widths and heights of 65..255 exercise the size bound.
constexpr int kMaxSidePx = 64;

inline DepthCodec::Params codecParams(DepthEncoding encoding) {
  DepthCodec::Params params;
  params.encoding = encoding;
  params.max_width_px = kMaxSidePx;
  params.max_height_px = kMaxSidePx;
  return params;
}

inline std::vector<uint8_t> makeInput(uint8_t encoding, uint8_t width, uint8_t height,
                                      const std::vector<uint8_t>& payload) {
  std::vector<uint8_t> input(kHeaderBytes + payload.size());
  input[0] = encoding;
  input[1] = width;
  input[2] = height;
  std::copy(payload.begin(), payload.end(), input.begin() + kHeaderBytes);
  return input;
}

}  // namespace kinfly::fuzz
