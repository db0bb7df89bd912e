// How fuzz_depth_decode reads its input, shared with the corpus generator: three bytes standing
// for the keyframe message's fields, then the payload.
//   byte 0: bits 0-6 the encoding, any value (4..127 must be rejected as kBadEncoding);
//           bit 7 (kWrapInZstd) set: bytes 3.. are the stream inside the zstd frame, and the
//           target compresses them before decoding, so that mutations reach the palette and RVL
//           codes of the zstd encodings instead of dying in zstd's own checks
//   byte 1: width in pixels, byte 2: height in pixels (0 and above kMaxSidePx must be rejected)
//   bytes 3..: the payload
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "kinfly/codec/depth_codec.h"

namespace kinfly::fuzz {

constexpr size_t kHeaderBytes = 3;
constexpr uint8_t kWrapInZstd = 0x80;
constexpr uint8_t kEncodingMask = 0x7f;
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
