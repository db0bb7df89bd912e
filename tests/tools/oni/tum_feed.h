// What the TUM feed driver (tum_feed_driver.cpp) and kinfly-oni-record share: the URI scheme and
// the stream properties through which the recorder learns when the feed is done and what it sent,
// and the digest both sides compute over the depth pixels.
#pragma once

#include <cstdint>
#include <cstring>

namespace kinfly::oni_tools {

// tumfeed://<path to a TUM RGB-D folder>
constexpr const char kTumFeedScheme[] = "tumfeed://";

// Stream properties beyond OpenNI2's own; the value is outside every range OpenNI2 and its
// drivers use (standard properties are small, PS1080's start at 0x1080xxxx).
enum TumFeedProperty : int {
  kTumFeedFramesTotal = 0x4b460001,  // int: frames in the folder
  kTumFeedFramesSent = 0x4b460002,   // int: frames handed to OpenNI2 since the stream started
  kTumFeedDigest = 0x4b460003,       // uint64_t: PixelDigest over every frame sent, in order
};

// FNV-1a over the depth pixels of successive frames, row by row without padding: the recorder
// compares what the feed sent with what OpenNI2's file driver replays, bit for bit.
class PixelDigest {
 public:
  void addFrame(const uint16_t* pixels, int width, int height, int stride_bytes) {
    const auto* bytes = reinterpret_cast<const uint8_t*>(pixels);
    const size_t row_bytes = static_cast<size_t>(width) * sizeof(uint16_t);
    for (int y = 0; y < height; ++y) {
      const uint8_t* row = bytes + static_cast<size_t>(y) * static_cast<size_t>(stride_bytes);
      for (size_t i = 0; i < row_bytes; ++i) value_ = (value_ ^ row[i]) * kPrime;
    }
  }
  uint64_t value() const { return value_; }

 private:
  static constexpr uint64_t kPrime = 0x100000001b3ull;
  uint64_t value_ = 0xcbf29ce484222325ull;
};

inline bool isTumFeedUri(const char* uri) {
  return std::strncmp(uri, kTumFeedScheme, sizeof kTumFeedScheme - 1) == 0;
}

}  // namespace kinfly::oni_tools
