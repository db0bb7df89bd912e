// libFuzzer target for DepthCodec::decode (input layout: depth_decode_input.h). Built with
// ASan and UBSan by `make fuzz`, which runs it on the committed corpus.
//
// Besides never reading or writing out of bounds, what decodes must survive its own round trip:
// encoded again in the same encoding it decodes to the same pixels. Codecs persist across inputs,
// as they do on a link, so leftovers from one payload that leak into the next are caught too.
#include <zstd.h>

#include <array>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <vector>

#include "depth_decode_input.h"
#include "kinfly/codec/depth_codec.h"
#include "kinfly/core/image.h"

using kinfly::DepthCodec;
using kinfly::DepthEncoding;

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < kinfly::fuzz::kHeaderBytes) return 0;
  static std::array<std::unique_ptr<DepthCodec>, kinfly::kDepthEncodingCount> codecs = [] {
    std::array<std::unique_ptr<DepthCodec>, kinfly::kDepthEncodingCount> all;
    for (int e = 0; e < kinfly::kDepthEncodingCount; ++e)
      all[e] = std::make_unique<DepthCodec>(kinfly::fuzz::codecParams(static_cast<DepthEncoding>(e)));
    return all;
  }();
  static kinfly::Image<uint16_t> decoded, again;
  static std::vector<uint8_t> payload, wrapped;

  const uint8_t encoding_byte = data[0] & kinfly::fuzz::kEncodingMask;
  const auto encoding = static_cast<DepthEncoding>(encoding_byte);
  const int width = data[1];
  const int height = data[2];
  const uint8_t* bytes = data + kinfly::fuzz::kHeaderBytes;
  size_t count = size - kinfly::fuzz::kHeaderBytes;
  if (data[0] & kinfly::fuzz::kWrapInZstd) {
    wrapped.resize(ZSTD_compressBound(count));
    count = ZSTD_compress(wrapped.data(), wrapped.size(), bytes, count, 1);
    if (ZSTD_isError(count)) std::abort();
    bytes = wrapped.data();
  }
  DepthCodec& codec = *codecs[encoding_byte % kinfly::kDepthEncodingCount];
  if (!codec.decode(bytes, count, encoding, width, height, &decoded).ok()) return 0;

  if (decoded.width() != width || decoded.height() != height) std::abort();
  if (!codec.encode(decoded.view(), &payload).ok()) std::abort();
  if (!codec.decode(payload.data(), payload.size(), encoding, width, height, &again).ok()) std::abort();
  if (std::memcmp(again.data(), decoded.data(), sizeof(uint16_t) * decoded.numPixels()) != 0)
    std::abort();
  return 0;
}
