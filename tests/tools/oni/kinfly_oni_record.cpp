// kinfly-oni-record: records the depth stream of an OpenNI2 device into an .oni file with the
// stock openni::Recorder, then replays the file through OpenNI2's own file driver and checks that
// every frame comes back. Prints one JSON object; exits 1 when the check fails (the file is kept,
// so a failed recording can still be looked at).
//
// The tests run it on the TUM feed (tumfeed://<folder>, tum_feed_driver.cpp): no sensor is
// attached where they run, and this is how they get a real recording of real depth. The feed
// tells how many frames it has and a digest of what it sent, so the check is bit for bit. Any
// other device (a real sensor, OpenNI2's "Dummy") is recorded for --frames frames and checked by
// count. It runs against the private OpenNI2 folder the build assembles next to it (CMakeLists.txt
// says why), so the feed driver is found without installing anything.
#include <CLI/CLI.hpp>
#include <OpenNI.h>

#include <chrono>
#include <cinttypes>
#include <cstdio>
#include <string>
#include <thread>

#include "tum_feed.h"

namespace kinfly::oni_tools {
namespace {

using Clock = std::chrono::steady_clock;
using namespace std::chrono_literals;

// Recorder::start() only queues a message to the recorder's thread, and frames arriving before
// that thread has handled it are not recorded: the stream starts after this much. The replay
// check catches a first frame lost all the same.
constexpr auto kRecorderStartup = 200ms;
// A device, or the replay, that delivers nothing for this long has stopped.
constexpr auto kSilence = 5s;
// OpenNI2's Dummy device stops its frame thread without joining it: give it a frame period.
constexpr auto kDriverStop = 100ms;

struct Replay {
  int recorded = 0;  // frames in the file's seek table
  int replayed = 0;  // frames the file driver delivered, in order
  bool in_order = true;
  uint64_t digest = 0;
  uint64_t first_us = 0, last_us = 0;
  std::string problem;
};

bool fail(const std::string& what) {
  std::fprintf(stderr, "kinfly-oni-record: %s: %s\n", what.c_str(),
               openni::OpenNI::getExtendedError());
  return false;
}

// Reads every frame of the recording once, as kinfly-fw does (manual playback: one frame per
// read, none overwritten).
Replay replay(const std::string& path) {
  Replay r;
  openni::Device file;
  openni::VideoStream stream;
  if (file.open(path.c_str()) != openni::STATUS_OK || file.getPlaybackControl() == nullptr) {
    r.problem = std::string("OpenNI2 cannot open it: ") + openni::OpenNI::getExtendedError();
    return r;
  }
  file.getPlaybackControl()->setSpeed(-1.0f);
  if (stream.create(file, openni::SENSOR_DEPTH) != openni::STATUS_OK ||
      stream.start() != openni::STATUS_OK) {
    r.problem = std::string("no depth stream: ") + openni::OpenNI::getExtendedError();
    return r;
  }
  r.recorded = file.getPlaybackControl()->getNumberOfFrames(stream);
  // The loop below stops at the count, so the driver may go round: at the end it then waits for
  // the next read instead of spinning over its streams, which it walks unlocked while destroy()
  // changes them (kinfly-fw's openni_source.cpp says more). Without a count nothing is read.
  file.getPlaybackControl()->setRepeatEnabled(true);
  PixelDigest digest;
  openni::VideoFrameRef frame;
  Clock::time_point last_frame = Clock::now();
  while (r.replayed < r.recorded && Clock::now() - last_frame < kSilence) {
    openni::VideoStream* streams[] = {&stream};
    int ready = -1;
    if (openni::OpenNI::waitForAnyStream(streams, 1, &ready, 100) != openni::STATUS_OK) continue;
    if (stream.readFrame(&frame) != openni::STATUS_OK) break;
    last_frame = Clock::now();
    ++r.replayed;
    r.in_order = r.in_order && frame.getFrameIndex() == r.replayed;
    if (r.replayed == 1) r.first_us = frame.getTimestamp();
    r.in_order = r.in_order && (r.replayed == 1 || frame.getTimestamp() > r.last_us);
    r.last_us = frame.getTimestamp();
    digest.addFrame(static_cast<const uint16_t*>(frame.getData()), frame.getWidth(),
                    frame.getHeight(), frame.getStrideInBytes());
  }
  r.digest = digest.value();
  frame.release();
  stream.stop();
  stream.destroy();
  file.close();
  return r;
}

struct Recorded {
  int sent = 0;  // the feed: frames it sent; a device: frames read while recording
  bool is_feed = false;  // the feed also says how many frames it has and what it sent
  int feed_total = 0;
  uint64_t feed_digest = 0;
};

bool record(const std::string& uri, const std::string& out, int frames, Recorded* recorded) {
  openni::Device device;
  openni::VideoStream stream;
  openni::Recorder recorder;
  if (device.open(uri.c_str()) != openni::STATUS_OK) return fail("cannot open " + uri);
  if (stream.create(device, openni::SENSOR_DEPTH) != openni::STATUS_OK)
    return fail(uri + " has no depth stream");
  if (!stream.isPropertySupported(ONI_STREAM_PROPERTY_CROPPING))
    std::fprintf(stderr, "kinfly-oni-record: %s reports no cropping: Debian's OniFile driver "
                         "drops every frame of such a recording when it replays it\n",
                 uri.c_str());
  recorded->is_feed =
      stream.getProperty(kTumFeedFramesTotal, &recorded->feed_total) == openni::STATUS_OK;
  if (!recorded->is_feed && frames <= 0) {
    std::fprintf(stderr, "kinfly-oni-record: %s is a device: --frames says how many to record\n",
                 uri.c_str());
    return false;
  }
  // Lossless: the recording must hold exactly the depth the device sent.
  if (recorder.create(out.c_str()) != openni::STATUS_OK ||
      recorder.attach(stream, false) != openni::STATUS_OK || recorder.start() != openni::STATUS_OK)
    return fail("cannot record to " + out);
  std::this_thread::sleep_for(kRecorderStartup);
  if (stream.start() != openni::STATUS_OK) return fail("cannot start the depth stream");

  Clock::time_point progress = Clock::now();
  int last_sent = 0;
  openni::VideoFrameRef frame;
  while (Clock::now() - progress < kSilence) {
    if (recorded->is_feed) {
      std::this_thread::sleep_for(10ms);
      stream.getProperty(kTumFeedFramesSent, &recorded->sent);
      if (recorded->sent == recorded->feed_total) break;
    } else {
      openni::VideoStream* streams[] = {&stream};
      int ready = -1;
      if (openni::OpenNI::waitForAnyStream(streams, 1, &ready, 100) == openni::STATUS_OK &&
          stream.readFrame(&frame) == openni::STATUS_OK)
        ++recorded->sent;
      if (recorded->sent >= frames) break;
    }
    if (recorded->sent != last_sent) progress = Clock::now();
    last_sent = recorded->sent;
  }
  if (recorded->is_feed) stream.getProperty(kTumFeedDigest, &recorded->feed_digest);
  // The recorder first: destroying it writes the seek table that frame counts come from.
  recorder.stop();
  recorder.destroy();
  frame.release();
  stream.stop();
  std::this_thread::sleep_for(kDriverStop);
  stream.destroy();
  device.close();
  return true;
}

int run(int argc, char** argv) {
  CLI::App app{"kinfly-oni-record: records an OpenNI2 device's depth stream into an .oni file, "
               "then replays it through OpenNI2's file driver to check every frame came back. "
               "Test tool: the TUM feed (tumfeed://FOLDER) turns a TUM RGB-D folder into a "
               "recording."};
  std::string uri, out;
  int frames = 0;
  app.add_option("--uri", uri, "OpenNI2 device URI: tumfeed://FOLDER, Dummy, a sensor's URI")
      ->required();
  app.add_option("--out", out, "the .oni file to write")->required();
  app.add_option("--frames", frames, "devices other than the feed: frames to record")
      ->check(CLI::PositiveNumber);
  CLI11_PARSE(app, argc, argv);

  if (openni::OpenNI::initialize() != openni::STATUS_OK) {
    fail("OpenNI2 did not initialise");
    return 1;
  }
  Recorded recorded;
  if (!record(uri, out, frames, &recorded)) {
    openni::OpenNI::shutdown();
    return 1;
  }
  const Replay r = replay(out);
  openni::OpenNI::shutdown();

  const bool digest_ok = !recorded.is_feed || r.digest == recorded.feed_digest;
  std::printf("{\"uri\": \"%s\", \"out\": \"%s\", \"sent\": %d, \"recorded\": %d, "
              "\"replayed\": %d, \"in_order\": %s, \"bit_exact\": %s, \"first_us\": %" PRIu64
              ", \"last_us\": %" PRIu64 "}\n",
              uri.c_str(), out.c_str(), recorded.sent, r.recorded, r.replayed,
              r.in_order ? "true" : "false",
              recorded.is_feed ? (digest_ok ? "true" : "false") : "null", r.first_us, r.last_us);
  std::string problem = r.problem;
  if (problem.empty() && recorded.is_feed && recorded.sent != recorded.feed_total)
    problem = "the feed sent " + std::to_string(recorded.sent) + " of its " +
              std::to_string(recorded.feed_total) + " frames";
  // A device may deliver more frames than were read while recording, never fewer.
  if (problem.empty() &&
      (recorded.is_feed ? r.recorded != recorded.sent : r.recorded < recorded.sent))
    problem = "the file holds " + std::to_string(r.recorded) + " frames of the " +
              std::to_string(recorded.sent) + " sent (the recorder was not ready in time?)";
  if (problem.empty() && r.replayed != r.recorded)
    problem = "OpenNI2's file driver replays " + std::to_string(r.replayed) + " of its " +
              std::to_string(r.recorded) + " frames";
  if (problem.empty() && !r.in_order) problem = "frames replay out of order";
  if (problem.empty() && !digest_ok) problem = "the replayed depth differs from what was sent";
  if (!problem.empty()) {
    std::fprintf(stderr, "kinfly-oni-record: %s: %s\n", out.c_str(), problem.c_str());
    return 1;
  }
  return 0;
}

}  // namespace
}  // namespace kinfly::oni_tools

int main(int argc, char** argv) { return kinfly::oni_tools::run(argc, argv); }
