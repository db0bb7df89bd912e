// kinfly_ground._native: the engine in shared/ for Python. Input arrays are read in place; a
// decoded image is copied once out of the codec's reused buffer into the array handed over.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>

#include <cstdint>
#include <cstring>
#include <memory>
#include <string>
#include <vector>

#include "kinfly/depth_codec.h"

namespace nb = nanobind;
using kinfly::CodecResult;
using kinfly::DepthCodec;
using kinfly::DepthEncoding;

namespace {

using DepthIn = nb::ndarray<const uint16_t, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using DepthOut = nb::ndarray<nb::numpy, uint16_t, nb::ndim<2>>;

DepthEncoding encodingOf(int value) {
  if (value < 0 || value >= kinfly::kDepthEncodingCount)
    throw nb::value_error(("unknown depth encoding " + std::to_string(value)).c_str());
  return static_cast<DepthEncoding>(value);
}

void check(const CodecResult& result, const char* what) {
  if (!result.ok())
    throw nb::value_error((std::string(what) + ": " + kinfly::toString(result.status) +
                           (*result.detail ? std::string(" (") + result.detail + ")" : ""))
                              .c_str());
}

// One codec object per Python object: it keeps its zstd contexts and buffers between frames.
class PyDepthCodec {
 public:
  PyDepthCodec(int encoding, int zstd_level, int max_width_px, int max_height_px) {
    DepthCodec::Params params;
    params.encoding = encodingOf(encoding);
    params.zstd_level = zstd_level;
    params.max_width_px = max_width_px;
    params.max_height_px = max_height_px;
    if (const std::string why = params.validate(); !why.empty())
      throw nb::value_error(why.c_str());
    codec_ = std::make_unique<DepthCodec>(params);
  }

  nb::bytes encode(DepthIn depth) {
    const kinfly::ImageView<const uint16_t> view(depth.data(), static_cast<int>(depth.shape(1)),
                                                 static_cast<int>(depth.shape(0)));
    check(codec_->encode(view, &payload_), "cannot encode depth");
    return nb::bytes(reinterpret_cast<const char*>(payload_.data()), payload_.size());
  }

  DepthOut decode(nb::bytes payload, int encoding, int width, int height) {
    check(codec_->decode(reinterpret_cast<const uint8_t*>(payload.c_str()), payload.size(),
                         encodingOf(encoding), width, height, &depth_),
          "cannot decode depth");
    auto* pixels = new uint16_t[depth_.numPixels()];
    std::memcpy(pixels, depth_.data(), depth_.numPixels() * sizeof(uint16_t));
    nb::capsule owner(pixels, [](void* p) noexcept { delete[] static_cast<uint16_t*>(p); });
    return DepthOut(pixels, {static_cast<size_t>(height), static_cast<size_t>(width)}, owner);
  }

 private:
  std::unique_ptr<DepthCodec> codec_;
  std::vector<uint8_t> payload_;
  kinfly::Image<uint16_t> depth_;
};

}  // namespace

NB_MODULE(_native, m) {
  m.doc() = "kinfly's engine (shared/) for the ground station";
  const DepthCodec::Params defaults;
  nb::class_<PyDepthCodec>(m, "DepthCodec",
                           "Lossless depth codec (RVL family, docs/wire.md); keeps its buffers.")
      .def(nb::init<int, int, int, int>(), nb::arg("encoding") = static_cast<int>(defaults.encoding),
           nb::arg("zstd_level") = defaults.zstd_level,
           nb::arg("max_width_px") = defaults.max_width_px,
           nb::arg("max_height_px") = defaults.max_height_px)
      .def("encode", &PyDepthCodec::encode, nb::arg("depth"),
           "uint16 (height, width) C-contiguous array -> payload bytes")
      .def("decode", &PyDepthCodec::decode, nb::arg("payload"), nb::arg("encoding"),
           nb::arg("width"), nb::arg("height"),
           "payload bytes -> uint16 (height, width) array; ValueError naming what is malformed");
}
