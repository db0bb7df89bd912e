// Depth sensors through OpenNI2 (the PS1080 driver: Kinect-class PrimeSense, Xtion, Orbbec), and
// .oni recordings through OpenNI2's own file driver. libusb adds what OpenNI2 does not give: which
// supported sensors are on the bus (so "none attached" and "attached but cannot be opened" read
// differently in the log) and a hot-plug notice, so a replugged sensor is retried at once
// instead of at the next backoff step.
#include <OpenNI.h>
#include <libusb.h>
#include <spdlog/spdlog.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <mutex>
#include <sstream>
#include <thread>

#include "depth_source.h"
#include "kinfly/fw/backoff.h"
#include "kinfly/link/signing.h"

namespace kinfly::fw {
namespace {

using Clock = std::chrono::steady_clock;
using namespace std::chrono_literals;

// USB vendors of the sensors the PS1080 driver serves (PrimeSense and ASUS Xtion share 1d27).
constexpr uint16_t kSensorVendors[] = {0x1d27, 0x045e, 0x2bc5};
// The longest one next() waits for a frame, so the capture thread sees a stop request in time.
constexpr int kReadTimeoutMs = 100;
// A connected sensor silent this long is taken as lost (closed, reopened with backoff). Longer
// than the SensorWatch's default stall timeout, so a stall is reported before the reconnect.
constexpr double kSilentLostS = 2.0;
// PrimeSense sensors see 58 x 45 degrees: fx = 320 / tan(29 deg) = 577 px at 640 wide.
constexpr float kPrimeSenseFxAt640 = 577.3f;
// A sensor whose reported field of view gives a focal length this far from the configured one
// is worth a warning: the map would be scaled wrong.
constexpr float kFovMismatch = 0.05f;

double secondsFrom(Clock::time_point t) {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

std::string hex4(uint16_t v) {
  char text[8];
  std::snprintf(text, sizeof text, "%04x", v);
  return text;
}

// OpenNI2's state is per process: initialised by the first source, never shut down before exit
// (its drivers' threads may still run while a stream is torn down).
bool initialiseOpenni(std::string* why) {
  static const openni::Status status = openni::OpenNI::initialize();
  if (status == openni::STATUS_OK) return true;
  *why = std::string("OpenNI2 did not initialise: ") + openni::OpenNI::getExtendedError();
  return false;
}

class UsbWatch {
 public:
  UsbWatch() {
    if (libusb_init(&context_) != 0) {
      context_ = nullptr;
      spdlog::info("openni: libusb unavailable: no USB presence check or hot-plug notice");
      return;
    }
    if (!libusb_has_capability(LIBUSB_CAP_HAS_HOTPLUG)) return;
    for (uint16_t vendor : kSensorVendors) {
      libusb_hotplug_callback_handle handle;
      if (libusb_hotplug_register_callback(context_, LIBUSB_HOTPLUG_EVENT_DEVICE_ARRIVED,
                                           LIBUSB_HOTPLUG_NO_FLAGS, vendor,
                                           LIBUSB_HOTPLUG_MATCH_ANY, LIBUSB_HOTPLUG_MATCH_ANY,
                                           &UsbWatch::onArrival, this, &handle) == 0)
        hotplug_ = true;
    }
  }
  ~UsbWatch() {
    if (context_) libusb_exit(context_);  // also drops the callbacks
  }
  UsbWatch(const UsbWatch&) = delete;
  UsbWatch& operator=(const UsbWatch&) = delete;

  // Waits up to timeout_ms; true if a supported sensor was plugged in since the last call.
  bool waitForArrival(int timeout_ms) {
    if (context_ && hotplug_) {
      timeval timeout{0, timeout_ms * 1000};
      libusb_handle_events_timeout_completed(context_, &timeout, nullptr);
    } else {
      std::this_thread::sleep_for(std::chrono::milliseconds(timeout_ms));
    }
    return arrived_.exchange(false);
  }

  // "vvvv:pppp" of every supported sensor on the bus, or why that is unknown.
  std::string attached() const {
    if (!context_) return "unknown (no libusb)";
    libusb_device** list = nullptr;
    const ssize_t n = libusb_get_device_list(context_, &list);
    std::string found;
    for (ssize_t i = 0; i < n; ++i) {
      libusb_device_descriptor d{};
      if (libusb_get_device_descriptor(list[i], &d) != 0) continue;
      for (uint16_t vendor : kSensorVendors)
        if (d.idVendor == vendor) found += (found.empty() ? "" : ", ") + hex4(d.idVendor) + ":" +
                                           hex4(d.idProduct);
    }
    if (n >= 0) libusb_free_device_list(list, 1);
    return found.empty() ? "none" : found;
  }

 private:
  static int LIBUSB_CALL onArrival(libusb_context*, libusb_device*, libusb_hotplug_event,
                                   void* self) {
    static_cast<UsbWatch*>(self)->arrived_ = true;
    return 0;  // stay registered
  }

  libusb_context* context_ = nullptr;
  bool hotplug_ = false;
  std::atomic<bool> arrived_{false};
};

class OpenniSource : public DepthSource, openni::OpenNI::DeviceDisconnectedListener {
 public:
  OpenniSource(const OpenniSourceParams& params, const PinholeCamera& camera, bool file)
      : params_(params), camera_(camera), file_(file),
        backoff_(params.reconnect_min_s, params.reconnect_max_s) {
    if (!file_) {
      usb_ = std::make_unique<UsbWatch>();
      openni::OpenNI::addDeviceDisconnectedListener(this);
    }
  }
  ~OpenniSource() override {
    close();
    if (!file_) openni::OpenNI::removeDeviceDisconnectedListener(this);
  }

  // Recordings must open at start; a sensor may come later.
  bool openRecording(std::string* why) { return connect(why); }

  const PinholeCamera& camera() const override { return camera_; }
  double depthScaleM() const override { return 0.001; }  // DEPTH_1_MM, the only mode asked for
  std::string describe() const override {
    return std::string(file_ ? "OpenNI2 recording " : "OpenNI2 sensor ") +
           (params_.uri.empty() ? "(first found)" : params_.uri);
  }
  int64_t connects() const override { return connects_; }
  bool waiting() const override { return !file_ && !connected_; }

  SourceStatus next(DepthCapture* out, std::string* why) override {
    if (!connected_) {
      if (file_) return SourceStatus::kEnd;
      const bool arrived = usb_->waitForArrival(kReadTimeoutMs);
      if (!arrived && Clock::now() < next_attempt_) {
        *why = waiting_why_;
        return SourceStatus::kWaiting;
      }
      std::string problem;
      if (!connect(&problem)) {
        const double wait_s = backoff_.next();
        next_attempt_ = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                           std::chrono::duration<double>(wait_s));
        std::ostringstream text;
        text << problem << "; retrying in " << wait_s << " s";
        waiting_why_ = *why = text.str();
        return SourceStatus::kWaiting;
      }
      backoff_.reset();
    }
    openni::VideoStream* streams[] = {&stream_};
    int ready = -1;
    if (lost_ || openni::OpenNI::waitForAnyStream(streams, 1, &ready, kReadTimeoutMs) !=
                     openni::STATUS_OK) {
      if (file_ && frames_read_ >= frames_in_file_) {
        close();
        return SourceStatus::kEnd;
      }
      if (lost_ || secondsFrom(last_frame_) > kSilentLostS) {
        *why = lost_ ? "depth sensor unplugged" : "depth sensor silent for 2 s";
        if (file_) {
          *why = "recording stopped delivering after " + std::to_string(frames_read_) + " of " +
                 std::to_string(frames_in_file_) + " frames";
          close();
          return SourceStatus::kEnd;
        }
        close();
        waiting_why_ = *why + ": closed, reconnecting";
        *why = waiting_why_;
        return SourceStatus::kWaiting;
      }
      *why = "no frame within 100 ms";
      return SourceStatus::kWaiting;
    }
    if (stream_.readFrame(&frame_) != openni::STATUS_OK) {
      *why = std::string("OpenNI2 could not read a frame: ") +
             openni::OpenNI::getExtendedError();
      return SourceStatus::kSkipped;
    }
    ++frames_read_;
    last_frame_ = Clock::now();
    return copyFrame(out, why);
  }

 private:
  void onDeviceDisconnected(const openni::DeviceInfo* info) override {
    if (connected_ && std::strcmp(info->getUri(), uri_.c_str()) == 0) lost_ = true;
  }

  bool connect(std::string* why) {
    std::string uri = params_.uri;
    if (uri.empty()) {
      openni::Array<openni::DeviceInfo> devices;
      openni::OpenNI::enumerateDevices(&devices);
      if (devices.getSize() == 0) {
        *why = "no depth sensor: OpenNI2 lists none (supported sensors on USB: " +
               usb_->attached() + ")";
        return false;
      }
      uri = devices[0].getUri();
    }
    if (device_.open(uri.c_str()) != openni::STATUS_OK) {
      *why = "cannot open depth sensor " + uri + ": " + openni::OpenNI::getExtendedError();
      if (usb_) *why += " (supported sensors on USB: " + usb_->attached() + ")";
      return false;
    }
    std::string problem = startDepth();
    if (!problem.empty()) {
      *why = uri + ": " + problem;
      device_.close();
      return false;
    }
    if (file_) {
      frames_in_file_ = device_.getPlaybackControl()->getNumberOfFrames(stream_);
      frames_read_ = 0;
    }
    uri_ = uri;
    connected_ = true;
    lost_ = false;
    have_time_origin_ = false;
    last_frame_ = Clock::now();
    ++connects_;
    spdlog::info("openni: {} streaming {}x{} depth (connection {})", uri, camera_.width,
                 camera_.height, connects_);
    return true;
  }

  // Picks the configured size in millimetres, starts the stream; empty on success.
  std::string startDepth() {
    if (file_) {
      openni::PlaybackControl* playback = device_.getPlaybackControl();
      playback->setRepeatEnabled(false);
      // Manual: one frame each time the reader asks, every frame exactly once (0, "fastest",
      // overwrites frames the reader has not taken yet). The capture thread does the pacing.
      playback->setSpeed(-1.0f);
    }
    const openni::SensorInfo* info = device_.getSensorInfo(openni::SENSOR_DEPTH);
    if (info == nullptr) return "has no depth sensor";
    const openni::Array<openni::VideoMode>& modes = info->getSupportedVideoModes();
    int best = -1;
    std::ostringstream offered;
    for (int i = 0; i < modes.getSize(); ++i) {
      const openni::VideoMode& m = modes[i];
      offered << (i ? ", " : "") << m.getResolutionX() << "x" << m.getResolutionY() << "@"
              << m.getFps() << (m.getPixelFormat() == openni::PIXEL_FORMAT_DEPTH_1_MM ? " mm"
                                                                                       : " other");
      if (m.getResolutionX() != camera_.width || m.getResolutionY() != camera_.height ||
          m.getPixelFormat() != openni::PIXEL_FORMAT_DEPTH_1_MM)
        continue;
      if (best < 0 || std::abs(m.getFps() - 30) < std::abs(modes[best].getFps() - 30)) best = i;
    }
    if (best < 0)
      return "offers no " + std::to_string(camera_.width) + "x" +
             std::to_string(camera_.height) + " millimetre depth mode (source.width, " +
             "source.height); it offers " + offered.str();
    if (stream_.create(device_, openni::SENSOR_DEPTH) != openni::STATUS_OK)
      return std::string("cannot create the depth stream: ") +
             openni::OpenNI::getExtendedError();
    // Recordings replay the mode they were made with; drivers without the properties (OpenNI2's
    // test device) refuse these calls, which changes nothing.
    if (!file_) {
      stream_.setVideoMode(modes[best]);
      stream_.setMirroringEnabled(false);  // the optical frame has x to the right
    }
    if (stream_.start() != openni::STATUS_OK) {
      std::string problem =
          std::string("cannot start the depth stream: ") + openni::OpenNI::getExtendedError();
      stream_.destroy();
      return problem;
    }
    const float hfov_rad = stream_.getHorizontalFieldOfView();
    if (hfov_rad > 0.f && hfov_rad < 3.f) {
      const float fx = 0.5f * static_cast<float>(camera_.width) / std::tan(0.5f * hfov_rad);
      if (std::abs(fx - camera_.fx) > kFovMismatch * camera_.fx)
        spdlog::warn("openni: the sensor's {:.1f} deg field of view means fx = {:.1f} px, but "
                     "the engine uses {:.1f} px: set source.intrinsics",
                     hfov_rad * 57.29578f, fx, camera_.fx);
    }
    return {};
  }

  void close() {
    if (!connected_) return;
    stream_.stop();
    // Some drivers (OpenNI2's test device) stop their frame thread without joining it; give it
    // a frame period to finish before the stream goes away.
    std::this_thread::sleep_for(100ms);
    stream_.destroy();
    frame_.release();
    device_.close();
    connected_ = false;
  }

  SourceStatus copyFrame(DepthCapture* out, std::string* why) {
    if (frame_.getVideoMode().getPixelFormat() != openni::PIXEL_FORMAT_DEPTH_1_MM ||
        frame_.getWidth() != camera_.width || frame_.getHeight() != camera_.height ||
        frame_.getData() == nullptr ||
        frame_.getStrideInBytes() < camera_.width * static_cast<int>(sizeof(uint16_t)) ||
        frame_.getDataSize() < frame_.getStrideInBytes() * camera_.height) {
      *why = "frame " + std::to_string(frame_.getFrameIndex()) + " is " +
             std::to_string(frame_.getWidth()) + "x" + std::to_string(frame_.getHeight()) +
             " in pixel format " + std::to_string(frame_.getVideoMode().getPixelFormat()) +
             ", not " + std::to_string(camera_.width) + "x" + std::to_string(camera_.height) +
             " millimetres";
      return SourceStatus::kSkipped;
    }
    if (out->depth.width() != camera_.width || out->depth.height() != camera_.height)
      out->depth = Image<uint16_t>(camera_.width, camera_.height);
    const auto* bytes = static_cast<const uint8_t*>(frame_.getData());
    for (int y = 0; y < camera_.height; ++y)
      std::memcpy(out->depth.view().row(y), bytes + y * frame_.getStrideInBytes(),
                  static_cast<size_t>(camera_.width) * sizeof(uint16_t));
    // Device timestamps count from the sensor's own start: keep their spacing (no host
    // scheduling jitter) on the wall clock's epoch, re-anchored at every connection.
    const auto device_us = static_cast<int64_t>(frame_.getTimestamp());
    if (!have_time_origin_ || device_us <= last_device_us_) {
      time_offset_us_ = link::wallClockUtime() - device_us;
      have_time_origin_ = true;
    }
    last_device_us_ = device_us;
    out->utime = device_us + time_offset_us_;
    out->has_ground_truth = false;
    return SourceStatus::kFrame;
  }

  OpenniSourceParams params_;
  PinholeCamera camera_;
  bool file_;
  std::unique_ptr<UsbWatch> usb_;  // sensors only
  Backoff backoff_;
  Clock::time_point next_attempt_{};
  std::string waiting_why_, uri_;
  openni::Device device_;
  openni::VideoStream stream_;
  openni::VideoFrameRef frame_;
  bool connected_ = false;
  std::atomic<bool> lost_{false};  // set by OpenNI2's hot-plug thread
  Clock::time_point last_frame_{};
  int64_t connects_ = 0;
  int frames_in_file_ = 0, frames_read_ = 0;
  bool have_time_origin_ = false;
  int64_t time_offset_us_ = 0, last_device_us_ = 0;
};

}  // namespace

std::unique_ptr<DepthSource> openOpenniSource(const OpenniSourceParams& params,
                                              std::string* why) {
  PinholeCamera camera;
  const float scale = static_cast<float>(params.width_px) / 640.f;
  camera.fx = camera.fy = kPrimeSenseFxAt640 * scale;
  camera.cx = 0.5f * static_cast<float>(params.width_px - 1);
  camera.cy = 0.5f * static_cast<float>(params.height_px - 1);
  if (!params.intrinsics.empty() && !parseIntrinsics(params.intrinsics, &camera, why))
    return nullptr;
  camera.width = params.width_px;
  camera.height = params.height_px;
  if (*why = camera.validate(); !why->empty()) return nullptr;
  if (!initialiseOpenni(why)) return nullptr;
  const bool file = std::filesystem::is_regular_file(params.uri);
  if (!file && params.uri.size() > 4 && params.uri.compare(params.uri.size() - 4, 4, ".oni") == 0) {
    *why = "source.path: recording " + params.uri + " does not exist";
    return nullptr;
  }
  auto source = std::make_unique<OpenniSource>(params, camera, file);
  if (file && !source->openRecording(why)) return nullptr;
  return source;
}

}  // namespace kinfly::fw
