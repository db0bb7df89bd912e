// DepthCodec: bit-exact round trips of every encoding on synthetic Kinect frames and edge cases,
// hand-written payloads that pin the documented format (docs/wire.md), and rejection of every
// truncation, of seeded random corruptions and of oversize images. Under `make test-asan` the
// corruption tests are what shows the decoder never reads or writes out of bounds.
#include <gtest/gtest.h>
#include <zstd.h>

#include <cstring>
#include <random>
#include <vector>

#include "kinfly/codec/depth_codec.h"
#include "test_util.h"

namespace kinfly {
namespace {

// Seeded corruptions per encoding: enough to hit every check of the small payloads below many
// times over (the fuzz target covers the long tail), quick enough under ASan.
constexpr int kMutationsPerEncoding = 3000;

std::vector<DepthEncoding> allEncodings() {
  std::vector<DepthEncoding> all;
  for (int e = 0; e < kDepthEncodingCount; ++e) all.push_back(static_cast<DepthEncoding>(e));
  return all;
}

DepthCodec::Params paramsFor(DepthEncoding encoding) {
  DepthCodec::Params params;
  params.encoding = encoding;
  return params;
}

// One Kinect-noise frame of the test corner scene, TUM units (0.2 mm): smooth surfaces, depth
// edges and the quantisation that the palette exploits.
Image<uint16_t> sceneFrame(int width, int height, uint32_t seed) {
  PinholeCamera camera = test::tumCamera();
  const float scale = static_cast<float>(width) / static_cast<float>(camera.width);
  camera.fx *= scale;
  camera.fy *= scale;
  camera.cx *= scale;
  camera.cy *= scale;
  camera.width = width;
  camera.height = height;
  Image<uint16_t> raw(width, height);
  std::mt19937 rng(seed);
  SyntheticScene::cornerRoom().renderRawDepth(camera, Pose::Identity(), test::kRenderMaxDepthM,
                                     test::kTumDepthScale, &rng, raw.view());
  return raw;
}

// Uniform values with about `zero_fraction` of them 0: no structure for any predictor to use.
Image<uint16_t> randomFrame(int width, int height, double zero_fraction, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_int_distribution<int> value(0, 65535);
  std::bernoulli_distribution zero(zero_fraction);
  Image<uint16_t> image(width, height);
  for (int i = 0; i < image.numPixels(); ++i)
    image.data()[i] = zero(rng) ? 0 : static_cast<uint16_t>(value(rng));
  return image;
}

bool sameImage(const Image<uint16_t>& a, const Image<uint16_t>& b) {
  return a.width() == b.width() && a.height() == b.height() &&
         std::memcmp(a.data(), b.data(), sizeof(uint16_t) * static_cast<size_t>(a.numPixels())) == 0;
}

std::vector<uint8_t> encodeOrDie(DepthCodec* codec, const Image<uint16_t>& image) {
  std::vector<uint8_t> payload;
  const CodecResult r = codec->encode(image.view(), &payload);
  EXPECT_TRUE(r.ok()) << toString(r.status) << ": " << r.detail;
  return payload;
}

CodecResult decodeInto(DepthCodec* codec, const std::vector<uint8_t>& payload, size_t size,
                       DepthEncoding encoding, int width, int height, Image<uint16_t>* out) {
  return codec->decode(payload.data(), size, encoding, width, height, out);
}

// The format written out independently of the codec (docs/wire.md), so that the tests below pin
// the bytes on the wire and not only that the encoder and decoder agree with each other.
std::vector<uint8_t> rvlWords(const std::vector<uint32_t>& codes, uint32_t padding_nibble = 0) {
  std::vector<uint32_t> nibbles;
  for (uint32_t v : codes) {
    do {
      nibbles.push_back((v & 7u) | (v >= 8u ? 8u : 0u));
      v >>= 3;
    } while (v != 0);
  }
  while (nibbles.size() % 8 != 0) nibbles.push_back(padding_nibble);
  std::vector<uint8_t> bytes;
  for (size_t w = 0; w < nibbles.size(); w += 8) {
    uint32_t word = 0;
    for (size_t k = 0; k < 8; ++k) word = word << 4 | nibbles[w + k];
    for (int b = 0; b < 4; ++b) bytes.push_back(static_cast<uint8_t>(word >> (8 * b)));
  }
  return bytes;
}

std::vector<uint8_t> zstdFrame(const std::vector<uint8_t>& inner) {
  std::vector<uint8_t> frame(ZSTD_compressBound(inner.size()));
  const size_t n = ZSTD_compress(frame.data(), frame.size(), inner.data(), inner.size(), 1);
  EXPECT_FALSE(ZSTD_isError(n));
  frame.resize(n);
  return frame;
}

uint32_t zigzag(int d) { return d >= 0 ? 2u * static_cast<uint32_t>(d) : 2u * static_cast<uint32_t>(-d) - 1u; }

class DepthCodecEncodings : public ::testing::TestWithParam<DepthEncoding> {};

TEST_P(DepthCodecEncodings, RoundTripsBitExact) {
  std::vector<std::pair<std::string, Image<uint16_t>>> cases;
  cases.emplace_back("kinect scene 640x480", sceneFrame(640, 480, 1));
  cases.emplace_back("kinect scene 161x121 (odd)", sceneFrame(161, 121, 2));
  cases.emplace_back("all zero", Image<uint16_t>(64, 48, 0));
  cases.emplace_back("all 65535", Image<uint16_t>(64, 48, 65535));
  cases.emplace_back("single pixel 0", Image<uint16_t>(1, 1, 0));
  cases.emplace_back("single pixel 65535", Image<uint16_t>(1, 1, 65535));
  cases.emplace_back("one row", randomFrame(97, 1, 0.3, 3));
  cases.emplace_back("one column", randomFrame(1, 97, 0.3, 4));
  cases.emplace_back("random 37x23", randomFrame(37, 23, 0.3, 5));
  cases.emplace_back("random, no zeros", randomFrame(128, 96, 0.0, 6));
  cases.emplace_back("random, half zeros", randomFrame(128, 96, 0.5, 7));
  // Every pixel a run of its own and deltas of the full range: the longest codes and most pairs.
  Image<uint16_t> alternating(63, 17, 0);
  for (int i = 0; i < alternating.numPixels(); i += 2) alternating.data()[i] = i % 4 ? 1 : 65535;
  cases.emplace_back("alternating 0 / extremes", std::move(alternating));
  cases.emplace_back("largest accepted", randomFrame(1280, 1024, 0.2, 8));

  DepthCodec codec(paramsFor(GetParam()));
  std::vector<uint8_t> payload;
  Image<uint16_t> decoded;
  for (const auto& [name, image] : cases) {
    SCOPED_TRACE(name);
    ASSERT_TRUE(codec.encode(image.view(), &payload).ok());
    const CodecResult r = codec.decode(payload.data(), payload.size(), GetParam(), image.width(),
                                       image.height(), &decoded);
    ASSERT_TRUE(r.ok()) << toString(r.status) << ": " << r.detail;
    EXPECT_TRUE(sameImage(decoded, image));
  }
}

TEST_P(DepthCodecEncodings, RejectsEveryTruncationAndAnAppendedByte) {
  DepthCodec codec(paramsFor(GetParam()));
  const Image<uint16_t> image = sceneFrame(80, 60, 9);
  std::vector<uint8_t> payload = encodeOrDie(&codec, image);
  Image<uint16_t> out;
  for (size_t size = 0; size < payload.size(); ++size) {
    const CodecResult r = decodeInto(&codec, payload, size, GetParam(), 80, 60, &out);
    EXPECT_FALSE(r.ok()) << "accepted the first " << size << " of " << payload.size() << " bytes";
  }
  payload.push_back(0);
  EXPECT_FALSE(decodeInto(&codec, payload, payload.size(), GetParam(), 80, 60, &out).ok());
}

// Corrupted payloads must come back as a status or as some image of the right size; ASan and
// UBSan (make test-asan) turn any out-of-bounds access on the way into a failure.
TEST_P(DepthCodecEncodings, SurvivesSeededCorruption) {
  DepthCodec codec(paramsFor(GetParam()));
  const Image<uint16_t> image = sceneFrame(48, 36, 10);
  const std::vector<uint8_t> valid = encodeOrDie(&codec, image);
  std::mt19937 rng(11);
  Image<uint16_t> out;
  for (int m = 0; m < kMutationsPerEncoding; ++m) {
    std::vector<uint8_t> bad = valid;
    std::uniform_int_distribution<int> edits(1, 4);
    for (int e = edits(rng); e > 0; --e) {
      std::uniform_int_distribution<size_t> at(0, bad.size() - 1);
      switch (rng() % 4) {
        case 0: bad[at(rng)] ^= static_cast<uint8_t>(1u << (rng() % 8)); break;
        case 1: bad[at(rng)] = static_cast<uint8_t>(rng()); break;
        case 2: bad.insert(bad.begin() + static_cast<std::ptrdiff_t>(at(rng)), static_cast<uint8_t>(rng())); break;
        default: if (bad.size() > 1) bad.erase(bad.begin() + static_cast<std::ptrdiff_t>(at(rng))); break;
      }
    }
    // Some corruptions still decode (raw pixels, a flipped bit inside an RVL difference): to
    // other pixels, but never to another size.
    if (decodeInto(&codec, bad, bad.size(), GetParam(), 48, 36, &out).ok()) {
      EXPECT_EQ(out.width(), 48);
      EXPECT_EQ(out.height(), 36);
    }
  }
}

TEST_P(DepthCodecEncodings, RejectsOversizeAndEmptyImages) {
  DepthCodec::Params params = paramsFor(GetParam());
  params.max_width_px = 64;
  params.max_height_px = 32;
  DepthCodec codec(params);
  std::vector<uint8_t> payload;
  EXPECT_EQ(codec.encode(Image<uint16_t>(65, 1, 1).view(), &payload).status, CodecStatus::kBadSize);
  EXPECT_EQ(codec.encode(Image<uint16_t>(1, 33, 1).view(), &payload).status, CodecStatus::kBadSize);
  EXPECT_EQ(codec.encode(Image<uint16_t>().view(), &payload).status, CodecStatus::kBadSize);

  payload = encodeOrDie(&codec, Image<uint16_t>(64, 32, 5));
  Image<uint16_t> out(3, 3, 7);
  for (const auto& [w, h] : {std::pair{65, 32}, {64, 33}, {0, 32}, {64, -1}, {1 << 30, 1 << 30}}) {
    EXPECT_EQ(decodeInto(&codec, payload, payload.size(), GetParam(), w, h, &out).status,
              CodecStatus::kBadSize);
  }
  EXPECT_EQ(out.width(), 3) << "a rejected size must not resize the caller's image";
  // A smaller image than the payload holds is a mismatch, never a write past the image.
  EXPECT_FALSE(decodeInto(&codec, payload, payload.size(), GetParam(), 32, 32, &out).ok());
  EXPECT_TRUE(decodeInto(&codec, payload, payload.size(), GetParam(), 64, 32, &out).ok());
}

INSTANTIATE_TEST_SUITE_P(AllEncodings, DepthCodecEncodings, ::testing::ValuesIn(allEncodings()),
                         [](const auto& param_info) { return std::string(toString(param_info.param)); });

TEST(DepthCodec, WireValuesAndNamesAreFixed) {
  EXPECT_EQ(static_cast<int>(DepthEncoding::kRaw16), 0);
  EXPECT_EQ(static_cast<int>(DepthEncoding::kRvl), 1);
  EXPECT_EQ(static_cast<int>(DepthEncoding::kRvlZstd), 2);
  EXPECT_EQ(static_cast<int>(DepthEncoding::kPaletteRvlZstd), 3);
  for (DepthEncoding e : allEncodings()) {
    DepthEncoding parsed = DepthEncoding::kRaw16;
    EXPECT_TRUE(parseDepthEncoding(toString(e), &parsed));
    EXPECT_EQ(parsed, e);
  }
  DepthEncoding unchanged = DepthEncoding::kRvl;
  EXPECT_FALSE(parseDepthEncoding("png", &unchanged));
  EXPECT_EQ(unchanged, DepthEncoding::kRvl);
}

TEST(DepthCodec, ParamsValidate) {
  EXPECT_TRUE(DepthCodec::Params().validate().ok());
  DepthCodec::Params p;
  p.zstd_level = 0;
  EXPECT_FALSE(p.validate().ok());
  p = DepthCodec::Params();
  p.max_width_px = 0;
  EXPECT_FALSE(p.validate().ok());
  p = DepthCodec::Params();
  p.max_height_px = 8193;
  EXPECT_FALSE(p.validate().ok());
  p = DepthCodec::Params();
  p.encoding = static_cast<DepthEncoding>(kDepthEncodingCount);
  EXPECT_FALSE(p.validate().ok());
}

TEST(DepthCodec, RejectsUnknownEncoding) {
  DepthCodec codec(DepthCodec::Params{});
  const std::vector<uint8_t> payload(8, 0);
  Image<uint16_t> out;
  EXPECT_EQ(decodeInto(&codec, payload, payload.size(), static_cast<DepthEncoding>(4), 2, 2, &out).status,
            CodecStatus::kBadEncoding);
  EXPECT_EQ(decodeInto(&codec, payload, payload.size(), static_cast<DepthEncoding>(255), 2, 2, &out).status,
            CodecStatus::kBadEncoding);
}

// Wilson's paper, by hand: a 3x2 image [0 0 100 / 101 0 99] is the pairs (2 zeros, 2 nonzero:
// +100, +1), (1 zero, 1 nonzero: -2), each nonzero pixel a zigzagged difference from the
// previous nonzero pixel.
TEST(DepthCodec, RvlMatchesTheFormatByHand) {
  const std::vector<uint8_t> payload = rvlWords({2, 2, zigzag(100), zigzag(1), 1, 1, zigzag(-2)});
  Image<uint16_t> expected(3, 2, 0);
  expected(2, 0) = 100;
  expected(0, 1) = 101;
  expected(2, 1) = 99;

  DepthCodec codec(paramsFor(DepthEncoding::kRvl));
  EXPECT_EQ(encodeOrDie(&codec, expected), payload);
  Image<uint16_t> out;
  ASSERT_TRUE(decodeInto(&codec, payload, payload.size(), DepthEncoding::kRvl, 3, 2, &out).ok());
  EXPECT_TRUE(sameImage(out, expected));

  DepthCodec zstd_codec(paramsFor(DepthEncoding::kRvlZstd));
  const std::vector<uint8_t> framed = zstdFrame(payload);
  ASSERT_TRUE(decodeInto(&zstd_codec, framed, framed.size(), DepthEncoding::kRvlZstd, 3, 2, &out).ok());
  EXPECT_TRUE(sameImage(out, expected));
}

// The palette format by hand: palette {100, 101, 5000} as (3; 100, +1, +4899), then RVL over
// indices 1..3 where a pixel with a valid pixel above is predicted from that pixel's index.
// Image [100 101 0 / 5000 101 101]: pairs (0 zeros, 2 nonzero: 1-0, 2-1), (1 zero, 3 nonzero:
// 3 from above 1, 2 from above 2, 2 from the previous nonzero 2 since the pixel above is 0).
std::vector<uint32_t> paletteCodes() {
  return {3, 100, 1, 4899, 0, 2, zigzag(1), zigzag(1), 1, 3, zigzag(2), zigzag(0), zigzag(0)};
}

TEST(DepthCodec, PaletteRvlMatchesTheFormatByHand) {
  Image<uint16_t> expected(3, 2, 0);
  expected(0, 0) = 100;
  expected(1, 0) = 101;
  expected(0, 1) = 5000;
  expected(1, 1) = 101;
  expected(2, 1) = 101;
  DepthCodec codec(paramsFor(DepthEncoding::kPaletteRvlZstd));
  const std::vector<uint8_t> payload = zstdFrame(rvlWords(paletteCodes()));
  Image<uint16_t> out;
  const CodecResult r = decodeInto(&codec, payload, payload.size(), DepthEncoding::kPaletteRvlZstd, 3, 2, &out);
  ASSERT_TRUE(r.ok()) << toString(r.status) << ": " << r.detail;
  EXPECT_TRUE(sameImage(out, expected));

  // The encoder writes the same stream (zstd's bytes may differ by version, the content not).
  const std::vector<uint8_t> encoded = encodeOrDie(&codec, expected);
  std::vector<uint8_t> inner(ZSTD_getFrameContentSize(encoded.data(), encoded.size()));
  ASSERT_EQ(ZSTD_decompress(inner.data(), inner.size(), encoded.data(), encoded.size()), inner.size());
  EXPECT_EQ(inner, rvlWords(paletteCodes()));
}

// Each malformed stream names the check it fails.
TEST(DepthCodec, NamesWhatIsWrong) {
  struct Case {
    const char* what;
    DepthEncoding encoding;
    std::vector<uint8_t> payload;
    int width, height;
    CodecStatus expected;
  };
  const auto palette = [](std::vector<uint32_t> codes) { return zstdFrame(rvlWords(codes)); };
  std::vector<uint8_t> two_frames = palette(paletteCodes());
  const std::vector<uint8_t> second = two_frames;
  two_frames.insert(two_frames.end(), second.begin(), second.end());
  std::vector<uint8_t> cut = palette(paletteCodes());
  cut.pop_back();
  std::vector<uint8_t> rvl_tail = rvlWords({2, 2, zigzag(100), zigzag(1), 1, 1, zigzag(-2)});
  rvl_tail.insert(rvl_tail.end(), 4, 0);
  // The hand-made image's 9 nibbles take two words; the first ends one code before the last pixel.
  const std::vector<uint8_t> rvl_first_word(rvl_tail.begin(), rvl_tail.begin() + 4);

  const std::vector<Case> cases = {
      {"raw16 one byte short", DepthEncoding::kRaw16, std::vector<uint8_t>(11), 3, 2, CodecStatus::kSizeMismatch},
      {"rvl not whole words", DepthEncoding::kRvl, std::vector<uint8_t>(6), 3, 2, CodecStatus::kTruncated},
      {"rvl ends inside the image", DepthEncoding::kRvl, rvl_first_word, 3, 2, CodecStatus::kTruncated},
      {"rvl word after the last pixel", DepthEncoding::kRvl, rvl_tail, 3, 2, CodecStatus::kTrailingBytes},
      {"rvl nonzero padding", DepthEncoding::kRvl, rvlWords({6, 0}, 1), 3, 2, CodecStatus::kTrailingBytes},
      {"rvl zero run past the image", DepthEncoding::kRvl, rvlWords({7, 0}), 3, 2, CodecStatus::kSizeMismatch},
      {"rvl nonzero run past the image", DepthEncoding::kRvl, rvlWords({0, 7, 2, 0, 0, 0, 0, 0, 0}), 3, 2, CodecStatus::kSizeMismatch},
      {"rvl empty pair", DepthEncoding::kRvl, rvlWords({0, 0, 6, 0}), 3, 2, CodecStatus::kBadValue},
      {"rvl pixel decodes to 0", DepthEncoding::kRvl, rvlWords({0, 6, 0, 0, 0, 0, 0, 0}), 3, 2, CodecStatus::kBadValue},
      {"rvl pixel above 65535", DepthEncoding::kRvl, rvlWords({5, 1, zigzag(65536)}), 3, 2, CodecStatus::kBadValue},
      {"rvl code over 30 bits", DepthEncoding::kRvl, std::vector<uint8_t>(8, 0xff), 3, 2, CodecStatus::kBadValue},
      {"not a zstd frame", DepthEncoding::kRvlZstd, std::vector<uint8_t>(16, 0x55), 3, 2, CodecStatus::kZstdError},
      {"zstd frame cut short", DepthEncoding::kPaletteRvlZstd, cut, 3, 2, CodecStatus::kTruncated},
      {"two zstd frames", DepthEncoding::kPaletteRvlZstd, two_frames, 3, 2, CodecStatus::kTrailingBytes},
      {"zstd content larger than any 1x1 stream", DepthEncoding::kRvlZstd, zstdFrame(std::vector<uint8_t>(1 << 20)), 1, 1, CodecStatus::kBadHeader},
      {"palette larger than the image", DepthEncoding::kPaletteRvlZstd, palette({7, 1, 1, 1, 1, 1, 1, 1}), 3, 2, CodecStatus::kBadHeader},
      {"palette not increasing", DepthEncoding::kPaletteRvlZstd, palette({2, 100, 0, 6, 0}), 3, 2, CodecStatus::kBadHeader},
      {"palette past 65535", DepthEncoding::kPaletteRvlZstd, palette({2, 65535, 1, 6, 0}), 3, 2, CodecStatus::kBadHeader},
      {"index beyond the palette", DepthEncoding::kPaletteRvlZstd, palette({1, 100, 5, 1, zigzag(2)}), 3, 2, CodecStatus::kBadValue},
  };
  DepthCodec codec(DepthCodec::Params{});
  Image<uint16_t> out;
  for (const Case& c : cases) {
    const CodecResult r = decodeInto(&codec, c.payload, c.payload.size(), c.encoding, c.width, c.height, &out);
    EXPECT_EQ(r.status, c.expected) << c.what << ": got " << toString(r.status) << " (" << r.detail << ")";
  }
}

TEST(DepthCodec, RejectsZstdFrameWithoutContentSize) {
  const std::vector<uint8_t> inner = rvlWords(paletteCodes());
  ZSTD_CCtx* cctx = ZSTD_createCCtx();
  ZSTD_CCtx_setParameter(cctx, ZSTD_c_contentSizeFlag, 0);
  std::vector<uint8_t> frame(ZSTD_compressBound(inner.size()));
  ZSTD_outBuffer out_buffer{frame.data(), frame.size(), 0};
  ZSTD_inBuffer in_buffer{inner.data(), inner.size(), 0};
  ASSERT_EQ(ZSTD_compressStream2(cctx, &out_buffer, &in_buffer, ZSTD_e_end), 0u);
  ZSTD_freeCCtx(cctx);
  frame.resize(out_buffer.pos);
  ASSERT_EQ(ZSTD_getFrameContentSize(frame.data(), frame.size()), ZSTD_CONTENTSIZE_UNKNOWN);

  DepthCodec codec(DepthCodec::Params{});
  Image<uint16_t> out;
  EXPECT_EQ(decodeInto(&codec, frame, frame.size(), DepthEncoding::kPaletteRvlZstd, 3, 2, &out).status,
            CodecStatus::kBadHeader);
}

// One codec carries frames of different sizes and encodings back to back: nothing left over from
// one frame (palette table, scratch stream) may leak into the next.
TEST(DepthCodec, FramesAreIndependent) {
  DepthCodec codec(paramsFor(DepthEncoding::kPaletteRvlZstd));
  Image<uint16_t> out;
  std::vector<uint8_t> payload;
  for (uint32_t seed = 20; seed < 26; ++seed) {
    const int width = 40 + 13 * static_cast<int>(seed % 3);
    const Image<uint16_t> image = seed % 2 ? sceneFrame(width, 30, seed) : randomFrame(width, 30, 0.2, seed);
    ASSERT_TRUE(codec.encode(image.view(), &payload).ok());
    ASSERT_TRUE(codec.decode(payload.data(), payload.size(), DepthEncoding::kPaletteRvlZstd, width, 30, &out).ok());
    EXPECT_TRUE(sameImage(out, image)) << "seed " << seed;
  }
}

}  // namespace
}  // namespace kinfly
