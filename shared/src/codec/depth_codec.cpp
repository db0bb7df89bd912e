#include "kinfly/codec/depth_codec.h"

#define ZSTD_STATIC_LINKING_ONLY  // ZSTD_initStaticCCtx, ZSTD_estimateCCtxSize: a fixed workspace
#include <zstd.h>
#include <zstd_errors.h>

#include <algorithm>
#include <cassert>
#include <cstring>
#include <sstream>

// Raw16 is memcpy and RVL words are assembled byte by byte, but a big-endian host has not been
// tested; both targets (x86-64 ground, aarch64 drone) are little-endian.
static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__, "depth codec tested on little-endian only");

namespace kinfly {

namespace {

constexpr uint32_t kMaxPaletteSize = 65535;   // every nonzero uint16 value
constexpr int kMaxSidePx = 8192;              // Params' range for max_width_px / max_height_px
// Longest code a stream may hold: 30 bits in 10 nibbles of 3. A code is a run length
// (<= 8192^2 = 2^26 pixels), a zigzagged difference (< 2^17) or a palette entry (< 2^16).
constexpr int kMaxNibblesPerCode = 10;
constexpr size_t kMaxCodeBytes = 5;

uint32_t zigzag(int32_t delta) {
  return (static_cast<uint32_t>(delta) << 1) ^ (delta < 0 ? ~0u : 0u);
}
int64_t unzigzag(uint32_t code) {
  return static_cast<int64_t>(code >> 1) ^ -static_cast<int64_t>(code & 1);
}

// Largest stream a zstd frame may hold for an image of n pixels: each pixel gives at most three
// codes (its difference and the two runs of the pair it may start), plus a palette. Only a bound
// on what a hostile frame can make the receiver allocate; real frames need ~0.4 bytes per pixel.
size_t maxInnerBytes(size_t n) { return (3 * n + kMaxPaletteSize + 1) * kMaxCodeBytes + 4; }

// Writes into a vector whose size is the writable area, growing it only when a reservation does
// not fit, so that a buffer reused across frames stops allocating after the largest frame.
class ByteSink {
 public:
  explicit ByteSink(std::vector<uint8_t>* buffer) : buffer_(buffer) {
    buffer_->resize(buffer_->capacity());
    data_ = buffer_->data();
  }
  void reserve(size_t bytes) {
    if (used_ + bytes <= buffer_->size()) return;
    buffer_->resize(std::max(2 * buffer_->size(), used_ + bytes));
    data_ = buffer_->data();
  }
  void put(uint8_t byte) { data_[used_++] = byte; }
  size_t used() const { return used_; }

 private:
  std::vector<uint8_t>* buffer_;
  uint8_t* data_;
  size_t used_ = 0;
};

// Wilson's EncodeVLE: 3 value bits per nibble, low bits first, the high bit set when more
// follow; the first nibble of each 32-bit word is its top nibble. Words are little-endian.
class NibbleWriter {
 public:
  explicit NibbleWriter(ByteSink* sink) : sink_(sink) {}
  // Room for `codes` more codes, the word in progress (up to 7 nibbles of earlier codes) and
  // the padded last word: ceil((7 + 10 codes) / 8) words <= 5 codes + 8 bytes.
  void reserveCodes(size_t codes) { sink_->reserve(codes * kMaxCodeBytes + 8); }
  void putCode(uint32_t value) {
    do {
      uint32_t nibble = value & 7u;
      value >>= 3;
      if (value != 0) nibble |= 8u;
      word_ = (word_ << 4) | nibble;
      if (++nibbles_ == 8) flushWord();
    } while (value != 0);
  }
  void finish() {
    if (nibbles_ == 0) return;
    word_ <<= 4 * (8 - nibbles_);
    flushWord();
  }

 private:
  void flushWord() {
    for (int shift = 0; shift < 32; shift += 8) sink_->put(static_cast<uint8_t>(word_ >> shift));
    word_ = 0;
    nibbles_ = 0;
  }
  ByteSink* sink_;
  uint32_t word_ = 0;
  int nibbles_ = 0;
};

class NibbleReader {
 public:
  NibbleReader(const uint8_t* data, size_t size) : next_(data), end_(data + size) {}
  CodecResult getCode(uint32_t* value) {
    uint32_t v = 0;
    for (int i = 0; i < kMaxNibblesPerCode; ++i) {
      if (nibbles_ == 0) {
        if (end_ - next_ < 4) return {CodecStatus::kTruncated, "RVL stream ends inside a code"};
        word_ = static_cast<uint32_t>(next_[0]) | static_cast<uint32_t>(next_[1]) << 8 |
                static_cast<uint32_t>(next_[2]) << 16 | static_cast<uint32_t>(next_[3]) << 24;
        next_ += 4;
        nibbles_ = 8;
      }
      const uint32_t nibble = word_ >> 28;
      word_ <<= 4;
      --nibbles_;
      v |= (nibble & 7u) << (3 * i);
      if ((nibble & 8u) == 0) {
        *value = v;
        return {};
      }
    }
    return {CodecStatus::kBadValue, "RVL code longer than 30 bits"};
  }
  // The encoder pads the last word with zero nibbles and writes nothing after it.
  CodecResult finish() const {
    if (word_ != 0) return {CodecStatus::kTrailingBytes, "nonzero padding after the last pixel"};
    if (next_ != end_) return {CodecStatus::kTrailingBytes, "RVL words after the last pixel"};
    return {};
  }

 private:
  const uint8_t* next_;
  const uint8_t* end_;
  uint32_t word_ = 0;
  int nibbles_ = 0;
};

// Wilson's CompressRVL scan: per pair, the length of a run of
// zeros, the length of the run of nonzero pixels after it, then each nonzero pixel's zigzagged
// difference from its prediction. RVL predicts the previous nonzero pixel in scan order; with
// kFromAbove the pixel above is used where it is valid (rows of a depth image resemble each
// other more than a pixel resembles the one before a hole). `symbol` maps a depth value to the
// coded value (the value itself, or its palette index).
template <bool kFromAbove, typename SymbolOf>
void encodeRvlScan(ImageView<const uint16_t> depth, SymbolOf symbol, NibbleWriter* out) {
  const uint16_t* px = depth.data();
  const size_t n = static_cast<size_t>(depth.numPixels());
  const size_t width = static_cast<size_t>(depth.width());
  int32_t previous = 0;
  size_t i = 0;
  while (i < n) {
    const size_t zeros_begin = i;
    while (i < n && px[i] == 0) ++i;
    const size_t run_begin = i;
    while (i < n && px[i] != 0) ++i;
    out->reserveCodes(2 + (i - run_begin));
    out->putCode(static_cast<uint32_t>(run_begin - zeros_begin));
    out->putCode(static_cast<uint32_t>(i - run_begin));
    for (size_t j = run_begin; j < i; ++j) {
      const int32_t current = symbol(px[j]);
      int32_t prediction = previous;
      if (kFromAbove && j >= width && px[j - width] != 0) prediction = symbol(px[j - width]);
      out->putCode(zigzag(current - prediction));
      previous = current;
    }
  }
  out->finish();
}

// The inverse of encodeRvlScan into `out` (coded values, not yet mapped through a palette).
// Every coded value must lie in [1, max_symbol], every run inside the image, and every pair must
// cover a pixel (which also bounds the loop by the image size, whatever the stream holds).
template <bool kFromAbove>
CodecResult decodeRvlScan(NibbleReader* in, int64_t max_symbol, ImageView<uint16_t> out) {
  uint16_t* px = out.data();
  const size_t n = static_cast<size_t>(out.numPixels());
  const size_t width = static_cast<size_t>(out.width());
  int64_t previous = 0;
  size_t i = 0;
  while (i < n) {
    uint32_t zeros = 0;
    uint32_t nonzeros = 0;
    if (CodecResult r = in->getCode(&zeros); !r.ok()) return r;
    if (zeros > n - i) return {CodecStatus::kSizeMismatch, "zero run past the last pixel"};
    std::fill(px + i, px + i + zeros, uint16_t{0});
    i += zeros;
    if (CodecResult r = in->getCode(&nonzeros); !r.ok()) return r;
    if (nonzeros > n - i) return {CodecStatus::kSizeMismatch, "nonzero run past the last pixel"};
    if (zeros == 0 && nonzeros == 0) return {CodecStatus::kBadValue, "empty run pair"};
    for (const size_t run_end = i + nonzeros; i < run_end; ++i) {
      uint32_t code = 0;
      if (CodecResult r = in->getCode(&code); !r.ok()) return r;
      int64_t prediction = previous;
      if (kFromAbove && i >= width && px[i - width] != 0) prediction = px[i - width];
      const int64_t current = prediction + unzigzag(code);
      if (current < 1 || current > max_symbol)
        return {CodecStatus::kBadValue, "nonzero-run pixel decodes to 0 or beyond the maximum"};
      px[i] = static_cast<uint16_t>(current);
      previous = current;
    }
  }
  return in->finish();
}

}  // namespace

const char* toString(DepthEncoding encoding) {
  switch (encoding) {
    case DepthEncoding::kRaw16: return "raw16";
    case DepthEncoding::kRvl: return "rvl";
    case DepthEncoding::kRvlZstd: return "rvl_zstd";
    case DepthEncoding::kPaletteRvlZstd: return "palette_rvl_zstd";
  }
  return "unknown";
}

bool parseDepthEncoding(const std::string& name, DepthEncoding* encoding) {
  for (int e = 0; e < kDepthEncodingCount; ++e) {
    if (name == toString(static_cast<DepthEncoding>(e))) {
      *encoding = static_cast<DepthEncoding>(e);
      return true;
    }
  }
  return false;
}

const char* toString(CodecStatus status) {
  switch (status) {
    case CodecStatus::kOk: return "ok";
    case CodecStatus::kBadEncoding: return "bad encoding";
    case CodecStatus::kBadSize: return "bad image size";
    case CodecStatus::kTruncated: return "truncated";
    case CodecStatus::kTrailingBytes: return "trailing bytes";
    case CodecStatus::kSizeMismatch: return "size mismatch";
    case CodecStatus::kBadHeader: return "bad header";
    case CodecStatus::kBadValue: return "bad value";
    case CodecStatus::kZstdError: return "zstd error";
  }
  return "unknown";
}

Status DepthCodec::Params::validate() const {
  std::ostringstream why;
  if (static_cast<int>(encoding) >= kDepthEncodingCount) why << "encoding is not a DepthEncoding";
  else if (zstd_level < 1 || zstd_level > ZSTD_maxCLevel())
    why << "zstd_level must be in [1, " << ZSTD_maxCLevel() << "]";
  else if (max_width_px < 1 || max_width_px > kMaxSidePx)
    why << "max_width_px must be in [1, " << kMaxSidePx << "]";
  else if (max_height_px < 1 || max_height_px > kMaxSidePx)
    why << "max_height_px must be in [1, " << kMaxSidePx << "]";
  return why.str().empty() ? Status() : Status::error(why.str());
}

void DepthCodec::ZstdDeleter::operator()(ZSTD_CCtx_s* context) const { ZSTD_freeCCtx(context); }
void DepthCodec::ZstdDeleter::operator()(ZSTD_DCtx_s* context) const { ZSTD_freeDCtx(context); }

DepthCodec::DepthCodec(const Params& params)
    : params_(params),
      cctx_(ZSTD_createCCtx()),
      dctx_(ZSTD_createDCtx()),
      index_of_value_(65536, 0),
      palette_(kMaxPaletteSize + 1, 0) {
  assert(params_.validate().ok());
}

DepthCodec::~DepthCodec() = default;

CodecResult DepthCodec::checkSize(int width, int height) const {
  if (width < 1 || height < 1) return {CodecStatus::kBadSize, "width or height < 1"};
  if (width > params_.max_width_px || height > params_.max_height_px)
    return {CodecStatus::kBadSize, "width or height above the codec's maximum"};
  return {};
}

CodecResult DepthCodec::encode(ImageView<const uint16_t> depth, std::vector<uint8_t>* payload) {
  if (CodecResult r = checkSize(depth.width(), depth.height()); !r.ok()) return r;
  const size_t n = static_cast<size_t>(depth.numPixels());
  const auto same_value = [](uint16_t v) { return static_cast<int32_t>(v); };
  switch (params_.encoding) {
    case DepthEncoding::kRaw16:
      payload->resize(2 * n);
      std::memcpy(payload->data(), depth.data(), 2 * n);
      return {};
    case DepthEncoding::kRvl: {
      ByteSink sink(payload);
      NibbleWriter writer(&sink);
      encodeRvlScan<false>(depth, same_value, &writer);
      payload->resize(sink.used());
      return {};
    }
    case DepthEncoding::kRvlZstd: {
      ByteSink sink(&inner_);
      NibbleWriter writer(&sink);
      encodeRvlScan<false>(depth, same_value, &writer);
      return compressInner(sink.used(), payload);
    }
    case DepthEncoding::kPaletteRvlZstd: {
      // Kinect depth takes a few hundred of the 65536 values (disparity is quantised), so
      // neighbours one disparity step apart differ by one palette index but by tens to
      // hundreds of depth units: most differences shrink from 2-3 RVL nibbles to one.
      const uint16_t* px = depth.data();
      for (size_t i = 0; i < n; ++i) index_of_value_[px[i]] = 1;
      uint32_t size = 0;
      for (uint32_t v = 1; v <= kMaxPaletteSize; ++v) {
        if (index_of_value_[v] == 0) continue;
        index_of_value_[v] = static_cast<uint16_t>(++size);
        palette_[size] = static_cast<uint16_t>(v);
      }
      index_of_value_[0] = 0;
      ByteSink sink(&inner_);
      NibbleWriter writer(&sink);
      writer.reserveCodes(1 + size);
      writer.putCode(size);
      for (uint32_t k = 1; k <= size; ++k) writer.putCode(palette_[k] - palette_[k - 1]);
      const uint16_t* index = index_of_value_.data();
      encodeRvlScan<true>(depth, [index](uint16_t v) { return static_cast<int32_t>(index[v]); },
                          &writer);
      // Only the entries this frame set, so the next frame starts from an all-zero table.
      for (uint32_t k = 1; k <= size; ++k) index_of_value_[palette_[k]] = 0;
      return compressInner(sink.used(), payload);
    }
  }
  return {CodecStatus::kBadEncoding, "encoding is not a DepthEncoding"};
}

void DepthCodec::reserve(int width_px, int height_px, std::vector<uint8_t>* payload) {
  const size_t raw_bytes = 2 * static_cast<size_t>(width_px) * static_cast<size_t>(height_px);
  inner_.reserve(raw_bytes);
  payload->reserve(std::max(raw_bytes, ZSTD_compressBound(raw_bytes)));
  // zstd sizes its tables to each input's size class and reallocates its workspace when a frame
  // needs more than it has (or has long needed much less). A workspace made once, big enough for
  // any input at this level, never changes: a static context in it compresses to the same bytes.
  if (static_cctx_ == nullptr) {
    cctx_workspace_.resize((ZSTD_estimateCCtxSize(params_.zstd_level) + 7) / 8);
    static_cctx_ = ZSTD_initStaticCCtx(cctx_workspace_.data(), 8 * cctx_workspace_.size());
  }
}

CodecResult DepthCodec::compressInner(size_t inner_size, std::vector<uint8_t>* payload) {
  payload->resize(ZSTD_compressBound(inner_size));
  ZSTD_CCtx_s* cctx = static_cctx_ != nullptr ? static_cctx_ : cctx_.get();
  const size_t written = ZSTD_compressCCtx(cctx, payload->data(), payload->size(),
                                           inner_.data(), inner_size, params_.zstd_level);
  if (ZSTD_isError(written)) {
    payload->clear();
    return {CodecStatus::kZstdError, ZSTD_getErrorName(written)};
  }
  payload->resize(written);
  return {};
}

CodecResult DepthCodec::decompressInner(const uint8_t* data, size_t size, size_t max_inner_size,
                                        size_t* inner_size) {
  // One frame exactly filling the payload, declaring its size up front: the size is checked
  // against the image before anything is allocated or decompressed.
  const size_t frame_size = ZSTD_findFrameCompressedSize(data, size);
  if (ZSTD_isError(frame_size)) {
    if (ZSTD_getErrorCode(frame_size) == ZSTD_error_srcSize_wrong)
      return {CodecStatus::kTruncated, "zstd frame cut short"};
    return {CodecStatus::kZstdError, ZSTD_getErrorName(frame_size)};
  }
  if (frame_size != size) return {CodecStatus::kTrailingBytes, "bytes after the zstd frame"};
  const unsigned long long content_size = ZSTD_getFrameContentSize(data, size);
  if (content_size == ZSTD_CONTENTSIZE_UNKNOWN || content_size == ZSTD_CONTENTSIZE_ERROR)
    return {CodecStatus::kBadHeader, "zstd frame without its content size"};
  if (content_size > max_inner_size)
    return {CodecStatus::kBadHeader, "zstd content larger than the image can need"};
  if (inner_.size() < content_size) inner_.resize(content_size);
  const size_t got = ZSTD_decompressDCtx(dctx_.get(), inner_.data(), content_size, data, size);
  if (ZSTD_isError(got)) return {CodecStatus::kZstdError, ZSTD_getErrorName(got)};
  if (got != content_size) return {CodecStatus::kZstdError, "zstd frame shorter than declared"};
  *inner_size = got;
  return {};
}

CodecResult DepthCodec::decode(const uint8_t* data, size_t size, DepthEncoding encoding, int width,
                               int height, Image<uint16_t>* depth) {
  if (static_cast<int>(encoding) >= kDepthEncodingCount)
    return {CodecStatus::kBadEncoding, "encoding is not a DepthEncoding"};
  if (CodecResult r = checkSize(width, height); !r.ok()) return r;
  if (depth->width() != width || depth->height() != height) *depth = Image<uint16_t>(width, height);
  const size_t n = static_cast<size_t>(width) * static_cast<size_t>(height);
  // A zero-length payload has no data pointer to speak of; every encoding rejects it below.
  static const uint8_t kNoBytes[1] = {0};
  if (size == 0) data = kNoBytes;

  switch (encoding) {
    case DepthEncoding::kRaw16:
      if (size != 2 * n) return {CodecStatus::kSizeMismatch, "raw16 length is not 2 x width x height"};
      std::memcpy(depth->data(), data, size);
      return {};
    case DepthEncoding::kRvl: {
      if (size % 4 != 0) return {CodecStatus::kTruncated, "RVL payload not whole 32-bit words"};
      NibbleReader reader(data, size);
      return decodeRvlScan<false>(&reader, 65535, depth->view());
    }
    case DepthEncoding::kRvlZstd: {
      size_t inner_size = 0;
      if (CodecResult r = decompressInner(data, size, maxInnerBytes(n), &inner_size); !r.ok())
        return r;
      if (inner_size % 4 != 0) return {CodecStatus::kTruncated, "RVL stream not whole 32-bit words"};
      NibbleReader reader(inner_.data(), inner_size);
      return decodeRvlScan<false>(&reader, 65535, depth->view());
    }
    case DepthEncoding::kPaletteRvlZstd: {
      size_t inner_size = 0;
      if (CodecResult r = decompressInner(data, size, maxInnerBytes(n), &inner_size); !r.ok())
        return r;
      if (inner_size % 4 != 0) return {CodecStatus::kTruncated, "RVL stream not whole 32-bit words"};
      NibbleReader reader(inner_.data(), inner_size);
      uint32_t palette_size = 0;
      if (CodecResult r = reader.getCode(&palette_size); !r.ok()) return r;
      if (palette_size > kMaxPaletteSize || palette_size > n)
        return {CodecStatus::kBadHeader, "palette larger than 65535 or the pixel count"};
      for (uint32_t k = 1; k <= palette_size; ++k) {
        uint32_t gap = 0;
        if (CodecResult r = reader.getCode(&gap); !r.ok()) return r;
        if (gap == 0 || gap > kMaxPaletteSize - palette_[k - 1])
          return {CodecStatus::kBadHeader, "palette not increasing within 1..65535"};
        palette_[k] = static_cast<uint16_t>(palette_[k - 1] + gap);
      }
      if (CodecResult r = decodeRvlScan<true>(&reader, palette_size, depth->view()); !r.ok())
        return r;
      uint16_t* px = depth->data();
      const uint16_t* value_of = palette_.data();
      for (size_t i = 0; i < n; ++i) px[i] = value_of[px[i]];
      return {};
    }
  }
  return {CodecStatus::kBadEncoding, "encoding is not a DepthEncoding"};
}

}  // namespace kinfly
