// Writes the seed corpus of fuzz_depth_decode (tests/fuzz/corpus/depth_decode): small valid
// payloads of every encoding, the streams inside the zstd ones (kWrapInZstd) and a few malformed
// ones, each a file named after what it holds.
// Deterministic (fixed seeds), so rerunning it reproduces the committed files:
//   build/tests/make_depth_decode_corpus tests/fuzz/corpus/depth_decode
#include <zstd.h>

#include <cstdio>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include "depth_decode_input.h"
#include "kinfly/codec/depth_codec.h"
#include "kinfly/core/image.h"
#include "kinfly/synthetic/synthetic_scene.h"

namespace {

using kinfly::DepthEncoding;
using kinfly::Image;

bool writeFile(const std::string& path, const std::vector<uint8_t>& bytes) {
  std::ofstream out(path, std::ios::binary);
  out.write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
  return static_cast<bool>(out);
}

// A box in front of a wall seen by a 32x24 camera with Kinect noise: edges, holes, quantisation.
Image<uint16_t> sceneImage() {
  kinfly::PinholeCamera camera;
  camera.width = 32;
  camera.height = 24;
  camera.fx = camera.fy = 30.f;
  camera.cx = 15.5f;
  camera.cy = 11.5f;
  kinfly::SyntheticScene scene;
  scene.addPlane(Eigen::Vector3f(0.f, 0.f, -1.f), -2.5f);
  scene.addBox(Eigen::Vector3f(0.2f, 0.f, 1.5f), Eigen::Vector3f(0.3f, 0.3f, 0.3f));
  Image<uint16_t> depth(camera.width, camera.height);
  std::mt19937 rng(1);
  scene.renderRawDepth(camera, kinfly::Pose::Identity(), 2.0f, 1.0 / 5000.0, &rng, depth.view());
  return depth;
}

Image<uint16_t> randomImage(int width, int height) {
  std::mt19937 rng(2);
  Image<uint16_t> image(width, height);
  for (int i = 0; i < image.numPixels(); ++i)
    image.data()[i] = rng() % 3 == 0 ? 0 : static_cast<uint16_t>(rng());
  return image;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: %s OUTDIR\n", argv[0]);
    return 2;
  }
  const std::string dir = argv[1];
  struct Named {
    const char* name;
    Image<uint16_t> image;
  };
  std::vector<Named> images;
  images.push_back({"scene_32x24", sceneImage()});
  images.push_back({"random_7x5", randomImage(7, 5)});
  images.push_back({"zeros_8x8", Image<uint16_t>(8, 8, 0)});
  images.push_back({"pixel_1x1", Image<uint16_t>(1, 1, 4242)});

  int written = 0;
  bool ok = true;
  for (int e = 0; e < kinfly::kDepthEncodingCount; ++e) {
    const auto encoding = static_cast<DepthEncoding>(e);
    kinfly::DepthCodec codec(kinfly::fuzz::codecParams(encoding));
    std::vector<uint8_t> payload;
    for (const Named& n : images) {
      if (!codec.encode(n.image.view(), &payload).ok()) return 1;
      const auto w = static_cast<uint8_t>(n.image.width());
      const auto h = static_cast<uint8_t>(n.image.height());
      const std::string stem = dir + "/" + kinfly::toString(encoding) + "_" + n.name;
      ok &= writeFile(stem, kinfly::fuzz::makeInput(static_cast<uint8_t>(e), w, h, payload));
      ++written;
      if (n.name != std::string("scene_32x24")) continue;
      // The malformed ones, from the scene payload: cut in half, one byte too many, a flipped
      // byte in the middle, the size one row short.
      std::vector<uint8_t> half(payload.begin(), payload.begin() + static_cast<long>(payload.size() / 2));
      std::vector<uint8_t> longer = payload;
      longer.push_back(0);
      std::vector<uint8_t> flipped = payload;
      flipped[flipped.size() / 2] ^= 0x5a;
      ok &= writeFile(stem + "_truncated", kinfly::fuzz::makeInput(static_cast<uint8_t>(e), w, h, half));
      ok &= writeFile(stem + "_trailing", kinfly::fuzz::makeInput(static_cast<uint8_t>(e), w, h, longer));
      ok &= writeFile(stem + "_flipped", kinfly::fuzz::makeInput(static_cast<uint8_t>(e), w, h, flipped));
      ok &= writeFile(stem + "_short_size", kinfly::fuzz::makeInput(static_cast<uint8_t>(e), w, h - 1, payload));
      written += 4;
      if (encoding == DepthEncoding::kRvlZstd || encoding == DepthEncoding::kPaletteRvlZstd) {
        std::vector<uint8_t> inner(ZSTD_getFrameContentSize(payload.data(), payload.size()));
        if (ZSTD_decompress(inner.data(), inner.size(), payload.data(), payload.size()) != inner.size())
          return 1;
        ok &= writeFile(stem + "_inner", kinfly::fuzz::makeInput(static_cast<uint8_t>(e) | kinfly::fuzz::kWrapInZstd, w, h, inner));
        ++written;
      }
    }
  }
  ok &= writeFile(dir + "/bad_encoding", kinfly::fuzz::makeInput(200, 4, 4, std::vector<uint8_t>(32, 0)));
  ok &= writeFile(dir + "/oversize", kinfly::fuzz::makeInput(0, 255, 255, std::vector<uint8_t>(64, 1)));
  written += 2;
  if (!ok) {
    std::fprintf(stderr, "cannot write into %s\n", dir.c_str());
    return 1;
  }
  std::printf("wrote %d inputs into %s\n", written, dir.c_str());
  return 0;
}
