// Lossless depth image codec for the link: RVL (A. D. Wilson, "Fast Lossless Depth Image
// Compression", ISS 2017) and variants with a zstd stage after it. docs/wire.md gives every
// payload byte by byte, the measurements behind the default and why each choice was made.
//
// Payloads carry no size or version header: the message carries width, height and the encoding,
// and a new format gets a new encoding value. Decoding never reads or writes outside the payload
// or the output image, whatever the bytes; every malformed payload comes back as a status.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kinfly/core/image.h"
#include "kinfly/core/status.h"

// zstd's context types, declared here so that users of the codec do not include zstd.h.
struct ZSTD_CCtx_s;
struct ZSTD_DCtx_s;

namespace kinfly {

// The values travel on the wire (the keyframe message's encoding field): never renumber.
enum class DepthEncoding : uint8_t {
  kRaw16 = 0,          // uint16 little-endian, row-major
  kRvl = 1,            // Wilson's RVL exactly: 4-bit variable-length codes in 32-bit words
  kRvlZstd = 2,        // a zstd frame holding a kRvl payload
  kPaletteRvlZstd = 3, // a zstd frame holding a palette and RVL over palette indices (default)
};
constexpr int kDepthEncodingCount = 4;

const char* toString(DepthEncoding encoding);
// "raw16", "rvl", "rvl_zstd", "palette_rvl_zstd" -> the encoding; false for anything else.
bool parseDepthEncoding(const std::string& name, DepthEncoding* encoding);

enum class CodecStatus {
  kOk,
  kBadEncoding,    // an encoding value this build does not know
  kBadSize,        // width or height <= 0 or above Params::max_width_px / max_height_px
  kTruncated,      // the payload ends before width x height pixels are decoded
  kTrailingBytes,  // bytes left after the last pixel
  kSizeMismatch,   // a length disagrees with width x height (raw length, run past the image)
  kBadHeader,      // palette or zstd frame header malformed or out of bounds
  kBadValue,       // a decoded value the encoder cannot produce (see CodecResult::detail)
  kZstdError,      // zstd refused the frame (detail: zstd's error name)
};
const char* toString(CodecStatus status);

// A per-frame outcome, counted by the link, not a Status (kinfly/core/status.h): `detail` is
// static text so that a rejected frame costs no allocation.
struct CodecResult {
  CodecStatus status = CodecStatus::kOk;
  const char* detail = "";  // static text saying which check failed; never owned
  bool ok() const { return status == CodecStatus::kOk; }
};

// One codec per link endpoint: it owns the zstd contexts and the scratch buffers, so that after
// the first frame of a given size neither direction allocates.
class DepthCodec {
 public:
  struct Params {
    // What encode() writes. kPaletteRvlZstd is the only one that meets the link budget's 8x on
    // the TUM teddy sequence (docs/wire.md).
    DepthEncoding encoding = DepthEncoding::kPaletteRvlZstd;
    // [1, 19] zstd level of the zstd encodings; 1: level 3 compresses no better on the TUM
    // sequence (12.6x against 12.7x) and encodes 20% slower.
    int zstd_level = 1;
    // [px] 1..8192: largest image either direction accepts, so that a message's width and
    // height cannot make the receiver allocate without bound. Default: SXGA, above every
    // Kinect/OpenNI depth mode.
    int max_width_px = 1280;
    int max_height_px = 1024;
    Status validate() const;
  };

  // `params` must validate(); an invalid one is a programming error (asserted).
  explicit DepthCodec(const Params& params);
  ~DepthCodec();
  DepthCodec(const DepthCodec&) = delete;
  DepthCodec& operator=(const DepthCodec&) = delete;

  const Params& params() const { return params_; }

  // Replaces *payload with `depth` in params().encoding. The vector's capacity is kept, so a
  // payload reused across frames stops allocating once it has grown to the largest frame.
  CodecResult encode(ImageView<const uint16_t> depth, std::vector<uint8_t>* payload);

  // Makes room, here and in *payload, for encoding width x height images whose streams are up to
  // the raw image's size (real depth needs ~0.4 bytes a pixel, a fifth of that), so that a sender
  // encoding frame after frame never allocates. A frame needing more still encodes, growing the
  // buffers once.
  void reserve(int width_px, int height_px, std::vector<uint8_t>* payload);

  // Decodes `size` bytes at `data` into *depth, which is resized to width x height only when its
  // size differs. On failure *depth holds unspecified pixels (still width x height when the size
  // was accepted).
  CodecResult decode(const uint8_t* data, size_t size, DepthEncoding encoding, int width,
                     int height, Image<uint16_t>* depth);

 private:
  struct ZstdDeleter {
    void operator()(ZSTD_CCtx_s* context) const;
    void operator()(ZSTD_DCtx_s* context) const;
  };
  CodecResult checkSize(int width, int height) const;
  CodecResult compressInner(size_t inner_size, std::vector<uint8_t>* payload);
  // Decompresses the payload's one zstd frame into inner_[0, *inner_size).
  CodecResult decompressInner(const uint8_t* data, size_t size, size_t max_inner_size,
                              size_t* inner_size);

  Params params_;
  std::unique_ptr<ZSTD_CCtx_s, ZstdDeleter> cctx_;
  std::vector<uint64_t> cctx_workspace_;   // reserve(): zstd's fixed workspace, 8-byte aligned
  ZSTD_CCtx_s* static_cctx_ = nullptr;     // ... and the context in it (freed with it)
  std::unique_ptr<ZSTD_DCtx_s, ZstdDeleter> dctx_;
  std::vector<uint8_t> inner_;           // the stream inside the zstd frame, either direction
  std::vector<uint16_t> index_of_value_; // encoder: palette index + 1 per depth value, else 0
  std::vector<uint16_t> palette_;        // index + 1 -> depth value; [0] = 0 (invalid depth)
};

}  // namespace kinfly
