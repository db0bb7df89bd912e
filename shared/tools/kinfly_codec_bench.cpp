// kinfly-codec-bench: the depth codec over every frame of a TUM RGB-D folder. Prints one JSON
// object: compression ratio, encode and decode time per frame, whether every frame came back
// bit for bit, and the ratio of every other encoding (and of plain zstd) for context.
#include <CLI/CLI.hpp>
#include <zstd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <iostream>
#include <string>
#include <vector>

#include "kinfly/codec/depth_codec.h"
#include "kinfly/core/image.h"
#include "kinfly/io/png_io.h"
#include "kinfly/io/tum_dataset.h"
#include "percentile.h"

namespace {

using Clock = std::chrono::steady_clock;
using kinfly::DepthCodec;
using kinfly::DepthEncoding;
using kinfly::tools::percentile;

// The reference point: zstd at its fastest level on the raw 16-bit pixels.
constexpr int kPlainZstdLevel = 1;

int fail(const std::string& message) {
  std::cerr << "kinfly-codec-bench: error: " << message << "\n";
  return 1;
}

double msSince(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

size_t rawBytes(const kinfly::Image<uint16_t>& frame) {
  return static_cast<size_t>(frame.numPixels()) * sizeof(uint16_t);
}

// Total payload bytes of `frames` in `encoding`; 0 if a frame fails to encode.
size_t encodedBytes(const std::vector<kinfly::Image<uint16_t>>& frames, DepthEncoding encoding,
                    int zstd_level) {
  DepthCodec::Params params;
  params.encoding = encoding;
  params.zstd_level = zstd_level;
  DepthCodec codec(params);
  std::vector<uint8_t> payload;
  size_t total = 0;
  for (const auto& frame : frames) {
    if (!codec.encode(frame.view(), &payload).ok()) return 0;
    total += payload.size();
  }
  return total;
}

size_t plainZstdBytes(const std::vector<kinfly::Image<uint16_t>>& frames) {
  std::vector<uint8_t> out;
  size_t total = 0;
  for (const auto& frame : frames) {
    out.resize(ZSTD_compressBound(rawBytes(frame)));
    const size_t n = ZSTD_compress(out.data(), out.size(), frame.data(), rawBytes(frame),
                                   kPlainZstdLevel);
    if (ZSTD_isError(n)) return 0;
    total += n;
  }
  return total;
}

}  // namespace

int main(int argc, char** argv) {
  std::string tum_dir;
  std::string encoding_name = kinfly::toString(DepthCodec::Params().encoding);
  int zstd_level = DepthCodec::Params().zstd_level;
  int repeat = 3;
  int max_frames = 0;
  std::vector<std::string> encoding_names;
  for (int e = 0; e < kinfly::kDepthEncodingCount; ++e)
    encoding_names.push_back(kinfly::toString(static_cast<DepthEncoding>(e)));

  CLI::App app{
      "kinfly-codec-bench: encodes and decodes every depth frame of a TUM RGB-D folder with the\n"
      "link's depth codec on one thread and prints one JSON object: frames, raw and compressed\n"
      "bytes, ratio, encode_ms and decode_ms (median and p90 over frames x repeats, after one\n"
      "untimed warm-up frame), bit_exact (every decoded frame equals its PNG), and\n"
      "baseline_ratio (every encoding, and zstd level 1 on the raw pixels). Exits 1 unless\n"
      "every frame came back bit for bit."};
  app.add_option("--tum", tum_dir, "TUM RGB-D folder holding depth.txt and depth/*.png (16-bit)")
      ->required();
  app.add_option("--encoding", encoding_name, "the encoding to time")
      ->capture_default_str()
      ->check(CLI::IsMember(encoding_names));
  app.add_option("--zstd-level", zstd_level, "zstd level of the zstd encodings")
      ->capture_default_str()
      ->check(CLI::Range(1, ZSTD_maxCLevel()));
  app.add_option("--repeat", repeat, "encode and decode every frame this many times")
      ->capture_default_str()
      ->check(CLI::Range(1, 1000));
  app.add_option("--max-frames", max_frames, "use only the first N frames (0: all)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  CLI11_PARSE(app, argc, argv);

  DepthCodec::Params params;
  kinfly::parseDepthEncoding(encoding_name, &params.encoding);
  params.zstd_level = zstd_level;
  if (const kinfly::Status status = params.validate(); !status.ok()) return fail(status.message());

  std::vector<kinfly::TumDepthEntry> entries;
  if (const kinfly::Status status = kinfly::readTumDepthList(tum_dir, &entries); !status.ok())
    return fail(status.message());
  if (max_frames > 0 && static_cast<size_t>(max_frames) < entries.size()) entries.resize(max_frames);
  if (entries.empty()) return fail(tum_dir + "/depth.txt lists no frames");
  // PNG decoding is kept out of the timed loop.
  std::vector<kinfly::Image<uint16_t>> frames(entries.size());
  for (size_t i = 0; i < entries.size(); ++i)
    if (const kinfly::Status status = kinfly::loadDepthPng(entries[i].path, &frames[i]); !status.ok())
      return fail(status.message());

  DepthCodec codec(params);
  std::vector<uint8_t> payload;
  kinfly::Image<uint16_t> decoded;
  // The first frame grows the buffers; steady-state frames allocate nothing.
  if (!codec.encode(frames[0].view(), &payload).ok() ||
      !codec.decode(payload.data(), payload.size(), params.encoding, frames[0].width(),
                    frames[0].height(), &decoded).ok())
    return fail("warm-up frame failed");

  std::vector<double> encode_ms, decode_ms;
  size_t raw_bytes = 0, compressed_bytes = 0;
  std::vector<bool> frame_exact(frames.size(), true);  // over every repeat
  for (int r = 0; r < repeat; ++r) {
    for (size_t i = 0; i < frames.size(); ++i) {
      const kinfly::Image<uint16_t>& frame = frames[i];
      const Clock::time_point t0 = Clock::now();
      const kinfly::CodecResult encoded = codec.encode(frame.view(), &payload);
      encode_ms.push_back(msSince(t0));
      if (!encoded.ok())
        return fail(entries[i].path + ": encode: " + kinfly::toString(encoded.status) + ": " +
                    encoded.detail);
      const Clock::time_point t1 = Clock::now();
      const kinfly::CodecResult result = codec.decode(payload.data(), payload.size(), params.encoding,
                                                      frame.width(), frame.height(), &decoded);
      decode_ms.push_back(msSince(t1));
      const bool exact = result.ok() &&
                         std::memcmp(decoded.data(), frame.data(), rawBytes(frame)) == 0;
      if (!exact)
        std::cerr << "kinfly-codec-bench: " << entries[i].path << " not bit-exact ("
                  << kinfly::toString(result.status) << " " << result.detail << ")\n";
      frame_exact[i] = frame_exact[i] && exact;
      if (r == 0) {
        raw_bytes += rawBytes(frame);
        compressed_bytes += payload.size();
      }
    }
  }
  const size_t exact_frames = static_cast<size_t>(std::count(frame_exact.begin(), frame_exact.end(), true));
  const bool bit_exact = exact_frames == frames.size();
  std::printf("{\"encoding\": \"%s\", \"zstd_level\": %d, \"frames\": %zu, \"width\": %d, "
              "\"height\": %d, \"repeat\": %d,\n",
              encoding_name.c_str(), zstd_level, frames.size(), frames[0].width(),
              frames[0].height(), repeat);
  std::printf(" \"raw_bytes\": %zu, \"compressed_bytes\": %zu, \"ratio\": %.3f,\n", raw_bytes,
              compressed_bytes, static_cast<double>(raw_bytes) / static_cast<double>(compressed_bytes));
  std::printf(" \"encode_ms\": {\"median\": %.3f, \"p90\": %.3f}, "
              "\"decode_ms\": {\"median\": %.3f, \"p90\": %.3f},\n",
              percentile(encode_ms, 0.5), percentile(encode_ms, 0.9), percentile(decode_ms, 0.5),
              percentile(decode_ms, 0.9));
  std::printf(" \"bit_exact\": %s, \"bit_exact_frames\": %zu,\n", bit_exact ? "true" : "false",
              exact_frames);
  std::printf(" \"baseline_ratio\": {");
  for (int e = 0; e < kinfly::kDepthEncodingCount; ++e) {
    const auto encoding = static_cast<DepthEncoding>(e);
    std::printf("\"%s\": %.3f, ", kinfly::toString(encoding),
                static_cast<double>(raw_bytes) /
                    static_cast<double>(encodedBytes(frames, encoding, zstd_level)));
  }
  std::printf("\"zstd%d_raw16\": %.3f}}\n", kPlainZstdLevel,
              static_cast<double>(raw_bytes) / static_cast<double>(plainZstdBytes(frames)));
  return bit_exact ? 0 : 1;
}
