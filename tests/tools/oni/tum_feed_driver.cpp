// An OpenNI2 device driver that streams a TUM RGB-D folder as a depth sensor: URI
// tumfeed://<folder>, depth in millimetres (DEPTH_1_MM), device timestamps the folder's capture
// times in microseconds.
//
// It exists only for the tests. No depth sensor is attached where they run, and the stock
// openni::Recorder records only what an OpenNI2 device streams, so this device is how a real TUM
// sequence becomes a real .oni recording (kinfly-oni-record), which kinfly-fw then replays
// through OpenNI2's own file driver exactly as it would a recording of a Kinect. It is never
// installed and never built for the drone.
//
// It answers the stream properties Debian's OniFile driver needs to replay a recording made from
// it: cropping (without it OniFile silently drops every frame), mirroring, field of view, stride,
// and the value range (the maximum must be 65535: depth above the reported maximum comes back
// corrupted).
//
// Options after the folder let it stand in for a sensor on a cable in kinfly-fw's reconnect test
// (kinfly-fw run against the private OpenNI2 folder that holds this driver, CMakeLists.txt):
//   tumfeed://<folder>?live&unplug_after=N&away_s=S
//   live            frames at the pace of their capture times, as a sensor delivers them (without
//                   it, as fast as they decode: the recorder queues every one)
//   unplug_after=N  after its Nth frame the device is unplugged (OpenNI2 is told it is gone) and
//                   plugged back in away_s seconds later (default 1); once per process
#include <Driver/OniDriverAPI.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <cstring>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <new>
#include <sstream>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "kinfly/core/image.h"
#include "kinfly/io/png_io.h"
#include "kinfly/io/tum_dataset.h"
#include "tum_feed.h"

// ONI_EXPORT_DRIVER expects XnLib's allocation macros, which Debian does not ship.
#define XN_NEW(type, ...) new (std::nothrow) type(__VA_ARGS__)
#define XN_DELETE(p) delete (p)

namespace kinfly::oni_tools {
namespace {

// TUM PNGs hold 5000 units per metre, OpenNI2's DEPTH_1_MM 1000: one millimetre is 5 units.
constexpr unsigned kTumUnitsPerMm = 5;
// The field of view reported for the stream, from the Kinect's nominal focal length (TUM's
// default intrinsics, 525 px at 640 wide); kinfly-fw's tests pass the real ones.
constexpr double kNominalFocalPx = 525.0;
constexpr int kFps = 30;
// A live stream sleeps in steps this short, so stop() is never kept waiting long.
constexpr auto kLiveSleepStep = std::chrono::milliseconds(20);

using Clock = std::chrono::steady_clock;

struct FeedOptions {
  std::string folder;
  bool live = false;
  int unplug_after = 0;  // frames; 0: never
  double away_s = 1.0;   // [s]
};

// tumfeed://<folder>[?option&option=value...]; empty *problem on success.
FeedOptions parseUri(const char* uri, std::string* problem) {
  FeedOptions options;
  const std::string rest = uri + (sizeof kTumFeedScheme - 1);
  const size_t query = rest.find('?');
  options.folder = rest.substr(0, query);
  std::istringstream items(query == std::string::npos ? "" : rest.substr(query + 1));
  for (std::string item; std::getline(items, item, '&');) {
    const size_t eq = item.find('=');
    const std::string key = item.substr(0, eq);
    const std::string value = eq == std::string::npos ? "" : item.substr(eq + 1);
    char* end = nullptr;
    if (key == "live" && eq == std::string::npos) {
      options.live = true;
    } else if (key == "unplug_after") {
      options.unplug_after = static_cast<int>(std::strtol(value.c_str(), &end, 10));
      if (value.empty() || *end != '\0' || options.unplug_after < 1) *problem = item;
    } else if (key == "away_s") {
      options.away_s = std::strtod(value.c_str(), &end);
      if (value.empty() || *end != '\0' || !(options.away_s >= 0)) *problem = item;
    } else {
      *problem = item;
    }
    if (!problem->empty()) {
      *problem = "bad option \"" + *problem + "\" (live, unplug_after=N, away_s=S)";
      break;
    }
  }
  return options;
}

OniVideoMode depthMode(int width, int height) {
  OniVideoMode mode{};
  mode.pixelFormat = ONI_PIXEL_FORMAT_DEPTH_1_MM;
  mode.resolutionX = width;
  mode.resolutionY = height;
  mode.fps = kFps;
  return mode;
}

template <typename T>
OniStatus putProperty(void* data, int* size, const T& value) {
  if (*size != static_cast<int>(sizeof(T))) return ONI_STATUS_BAD_PARAMETER;
  std::memcpy(data, &value, sizeof(T));
  return ONI_STATUS_OK;
}

// One depth stream over the folder's frames, sent once each from start(). unplug() is asked
// after each frame once unplug_after frames are out; true means the cable is out and the stream
// goes quiet.
class TumFeedStream : public oni::driver::StreamBase {
 public:
  TumFeedStream(const std::vector<TumDepthEntry>* frames, int width, int height,
                const FeedOptions* options, std::function<bool()> unplug)
      : frames_(frames), width_(width), height_(height), options_(options),
        unplug_(std::move(unplug)) {}
  ~TumFeedStream() override { stop(); }
  TumFeedStream(const TumFeedStream&) = delete;
  TumFeedStream& operator=(const TumFeedStream&) = delete;

  OniStatus start() override {
    if (thread_.joinable()) return ONI_STATUS_OK;
    running_ = true;
    thread_ = std::thread([this] { sendAll(); });
    return ONI_STATUS_OK;
  }
  // Joins the sending thread, so the stream can be destroyed right after.
  void stop() override {
    running_ = false;
    if (thread_.joinable()) thread_.join();
  }

  OniBool isPropertySupported(int id) override {
    switch (id) {
      case ONI_STREAM_PROPERTY_VIDEO_MODE:
      case ONI_STREAM_PROPERTY_CROPPING:
      case ONI_STREAM_PROPERTY_MIRRORING:
      case ONI_STREAM_PROPERTY_HORIZONTAL_FOV:
      case ONI_STREAM_PROPERTY_VERTICAL_FOV:
      case ONI_STREAM_PROPERTY_MAX_VALUE:
      case ONI_STREAM_PROPERTY_MIN_VALUE:
      case ONI_STREAM_PROPERTY_STRIDE:
      case kTumFeedFramesTotal:
      case kTumFeedFramesSent:
      case kTumFeedDigest:
        return TRUE;
      default:
        return FALSE;
    }
  }

  OniStatus getProperty(int id, void* data, int* size) override {
    switch (id) {
      case ONI_STREAM_PROPERTY_VIDEO_MODE: return putProperty(data, size, videoMode());
      case ONI_STREAM_PROPERTY_CROPPING: {
        OniCropping cropping{};
        cropping.enabled = FALSE;
        cropping.width = width_;
        cropping.height = height_;
        return putProperty(data, size, cropping);
      }
      case ONI_STREAM_PROPERTY_MIRRORING: return putProperty(data, size, OniBool{FALSE});
      case ONI_STREAM_PROPERTY_HORIZONTAL_FOV: return putProperty(data, size, fovRad(width_));
      case ONI_STREAM_PROPERTY_VERTICAL_FOV: return putProperty(data, size, fovRad(height_));
      case ONI_STREAM_PROPERTY_MAX_VALUE: return putProperty(data, size, int{65535});
      case ONI_STREAM_PROPERTY_MIN_VALUE: return putProperty(data, size, int{0});
      case ONI_STREAM_PROPERTY_STRIDE: return putProperty(data, size, rowBytes());
      case kTumFeedFramesTotal: return putProperty(data, size, static_cast<int>(frames_->size()));
      case kTumFeedFramesSent: return putProperty(data, size, sent_.load());
      case kTumFeedDigest: return putProperty(data, size, digest_.load());
      default: return ONI_STATUS_NOT_SUPPORTED;
    }
  }

  // The one mode there is may be asked for; anything else is refused.
  OniStatus setProperty(int id, const void* data, int size) override {
    if (id != ONI_STREAM_PROPERTY_VIDEO_MODE || size != static_cast<int>(sizeof(OniVideoMode)))
      return ONI_STATUS_NOT_SUPPORTED;
    OniVideoMode asked;
    std::memcpy(&asked, data, sizeof asked);
    const OniVideoMode mode = videoMode();
    return asked.resolutionX == mode.resolutionX && asked.resolutionY == mode.resolutionY &&
                   asked.pixelFormat == mode.pixelFormat
               ? ONI_STATUS_OK
               : ONI_STATUS_NOT_SUPPORTED;
  }

  int getRequiredFrameSize() override { return rowBytes() * height_; }

 private:
  OniVideoMode videoMode() const { return depthMode(width_, height_); }
  int rowBytes() const { return width_ * static_cast<int>(sizeof(OniDepthPixel)); }
  static float fovRad(int pixels) {
    return static_cast<float>(2.0 * std::atan(0.5 * pixels / kNominalFocalPx));
  }

  void sendAll() {
    Image<uint16_t> png;
    PixelDigest digest;
    const Clock::time_point started = Clock::now();
    for (size_t i = 0; i < frames_->size() && running_; ++i) {
      const TumDepthEntry& entry = (*frames_)[i];
      if (options_->live) {
        const auto due = started + std::chrono::duration_cast<Clock::duration>(
                                       std::chrono::duration<double>(
                                           entry.timestamp_s - frames_->front().timestamp_s));
        while (running_ && Clock::now() < due)
          std::this_thread::sleep_for(
              std::min<Clock::duration>(kLiveSleepStep, due - Clock::now()));
      }
      if (const kinfly::Status loaded = loadDepthPng(entry.path, &png); !loaded.ok()) {
        std::fprintf(stderr, "tum feed: %s: frame not sent\n", loaded.message().c_str());
        continue;
      }
      if (png.width() != width_ || png.height() != height_) {
        std::fprintf(stderr, "tum feed: %s is %dx%d, the folder's first frame %dx%d: not sent\n",
                     entry.path.c_str(), png.width(), png.height(), width_, height_);
        continue;
      }
      OniFrame* frame = getServices().acquireFrame();
      if (frame == nullptr) break;
      auto* mm = static_cast<OniDepthPixel*>(frame->data);
      for (int k = 0; k < png.numPixels(); ++k)  // nearest millimetre
        mm[k] = static_cast<OniDepthPixel>((png.data()[k] + kTumUnitsPerMm / 2) / kTumUnitsPerMm);
      frame->dataSize = getRequiredFrameSize();
      frame->sensorType = ONI_SENSOR_DEPTH;
      frame->timestamp = static_cast<uint64_t>(std::llround(entry.timestamp_s * 1e6));
      frame->frameIndex = static_cast<int>(i) + 1;
      frame->videoMode = videoMode();
      frame->width = width_;
      frame->height = height_;
      frame->croppingEnabled = FALSE;
      frame->cropOriginX = frame->cropOriginY = 0;
      frame->stride = rowBytes();
      digest.addFrame(mm, width_, height_, rowBytes());
      raiseNewFrame(frame);
      getServices().releaseFrame(frame);
      digest_ = digest.value();
      ++sent_;
      if (options_->unplug_after > 0 && sent_ >= options_->unplug_after && unplug_()) return;
    }
  }

  const std::vector<TumDepthEntry>* frames_;  // the device's, which outlives its streams
  int width_, height_;
  const FeedOptions* options_;  // the device's too
  std::function<bool()> unplug_;
  std::thread thread_;
  std::atomic<bool> running_{false};
  std::atomic<int> sent_{0};
  std::atomic<uint64_t> digest_{PixelDigest().value()};
};

class TumFeedDevice : public oni::driver::DeviceBase {
 public:
  TumFeedDevice(std::vector<TumDepthEntry> frames, int width, int height, FeedOptions options,
                std::function<bool()> unplug)
      : frames_(std::move(frames)), width_(width), height_(height),
        options_(std::move(options)), unplug_(std::move(unplug)),
        mode_(depthMode(width, height)) {
    sensor_.sensorType = ONI_SENSOR_DEPTH;
    sensor_.numSupportedVideoModes = 1;
    sensor_.pSupportedVideoModes = &mode_;
  }

  OniStatus getSensorInfoList(OniSensorInfo** sensors, int* count) override {
    *sensors = &sensor_;
    *count = 1;
    return ONI_STATUS_OK;
  }
  oni::driver::StreamBase* createStream(OniSensorType type) override {
    if (type != ONI_SENSOR_DEPTH) return nullptr;
    return new (std::nothrow) TumFeedStream(&frames_, width_, height_, &options_, unplug_);
  }
  void destroyStream(oni::driver::StreamBase* stream) override { delete stream; }

 private:
  std::vector<TumDepthEntry> frames_;
  int width_, height_;
  FeedOptions options_;
  std::function<bool()> unplug_;
  OniVideoMode mode_;
  OniSensorInfo sensor_{};
};

class TumFeedDriver : public oni::driver::DriverBase {
 public:
  explicit TumFeedDriver(OniDriverServices* services) : DriverBase(services) {}
  ~TumFeedDriver() override { shutdown(); }
  TumFeedDriver(const TumFeedDriver&) = delete;
  TumFeedDriver& operator=(const TumFeedDriver&) = delete;

  // OpenNI2 asks every driver about a URI it has never listed; this one claims tumfeed://.
  OniStatus tryDevice(const char* uri) override {
    if (!isTumFeedUri(uri)) return ONI_STATUS_ERROR;
    OniDeviceInfo* info = nullptr;
    {
      const std::lock_guard<std::mutex> lock(mutex_);
      std::unique_ptr<OniDeviceInfo>& slot = infos_[uri];
      if (!slot) {
        slot = std::make_unique<OniDeviceInfo>();
        std::memset(slot.get(), 0, sizeof(OniDeviceInfo));
        std::snprintf(slot->uri, ONI_MAX_STR, "%s", uri);
        std::snprintf(slot->vendor, ONI_MAX_STR, "kinfly tests");
        std::snprintf(slot->name, ONI_MAX_STR, "TUM folder feed");
      }
      info = slot.get();
    }
    deviceConnected(info);
    return ONI_STATUS_OK;
  }

  oni::driver::DeviceBase* deviceOpen(const char* uri, const char* /*mode*/) override {
    if (!isTumFeedUri(uri)) return nullptr;
    std::string problem;
    FeedOptions options = parseUri(uri, &problem);
    std::vector<TumDepthEntry> frames;
    Image<uint16_t> first;
    if (problem.empty()) problem = readTumDepthList(options.folder, &frames).message();
    if (problem.empty()) problem = loadDepthPng(frames.front().path, &first).message();
    if (!problem.empty()) {
      getServices().errorLoggerAppend("tum feed: %s", problem.c_str());
      return nullptr;
    }
    const double away_s = options.away_s;
    return new (std::nothrow)
        TumFeedDevice(std::move(frames), first.width(), first.height(), std::move(options),
                      [this, key = std::string(uri), away_s] { return unplug(key, away_s); });
  }
  void deviceClose(oni::driver::DeviceBase* device) override { delete device; }

  void shutdown() override {
    {
      const std::lock_guard<std::mutex> lock(mutex_);
      shutting_down_ = true;
    }
    wake_.notify_all();
    if (replug_.joinable()) replug_.join();
    const std::lock_guard<std::mutex> lock(mutex_);
    infos_.clear();
  }

 private:
  // Called on a stream's thread; true if this pulled the cable (the first time only). OpenNI2
  // hears of it as of a sensor unplugged; away_s later the device announces itself again, as the
  // PS1080 driver does when a sensor is plugged back in (OpenNI2 reopens a device it was told
  // was gone only after that).
  bool unplug(const std::string& uri, double away_s) {
    OniDeviceInfo* info = nullptr;
    {
      const std::lock_guard<std::mutex> lock(mutex_);
      if (shutting_down_ || unplugged_) return false;
      unplugged_ = true;
      info = infos_[uri].get();
    }
    if (info == nullptr) return false;
    deviceDisconnected(info);
    const auto back = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                         std::chrono::duration<double>(away_s));
    const std::lock_guard<std::mutex> lock(mutex_);
    if (!shutting_down_)
      replug_ = std::thread([this, info, back] {
        std::unique_lock<std::mutex> wait(mutex_);
        if (wake_.wait_until(wait, back, [this] { return shutting_down_; })) return;
        wait.unlock();
        deviceConnected(info);
      });
    return true;
  }

  std::mutex mutex_;
  std::condition_variable wake_;
  bool shutting_down_ = false;
  std::map<std::string, std::unique_ptr<OniDeviceInfo>> infos_;  // OpenNI2 keeps the pointers
  bool unplugged_ = false;  // once per process
  std::thread replug_;
};

}  // namespace
}  // namespace kinfly::oni_tools

ONI_EXPORT_DRIVER(kinfly::oni_tools::TumFeedDriver)
