// Depth sensors through OpenNI2 (the PS1080 driver: Kinect-class PrimeSense, Xtion, Orbbec), and
// .oni recordings through OpenNI2's own file driver. libusb adds what OpenNI2 does not give: which
// supported sensors are on the bus (so "none attached" and "attached but cannot be opened" read
// differently in the log) and a USB hot-plug notice. That notice, or OpenNI2's own "device
// connected" event (which comes once its driver has taken the sensor on), has a replugged sensor
// retried at once instead of at the next backoff step.
#include <OpenNI.h>
#include <libusb.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <mutex>
#include <sstream>
#include <system_error>
#include <thread>

#include "kinfly/fw/backoff.h"
#include "kinfly/core/range_check.h"
#include "kinfly/sources/openni_source.h"
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

// OpenNI2's last error on one line: it comes indented with a tab and ends in a newline, which
// would split the log line.
std::string openniError() {
  std::string text = openni::OpenNI::getExtendedError();
  std::replace(text.begin(), text.end(), '\n', ' ');
  std::replace(text.begin(), text.end(), '\t', ' ');
  const size_t first = text.find_first_not_of(' ');
  if (first == std::string::npos) return "no detail from OpenNI2";
  return text.substr(first, text.find_last_not_of(' ') - first + 1);
}

// OpenNI2's state is per process: initialised by the first source, never shut down before exit
// (its drivers' threads may still run while a stream is torn down).
Status initialiseOpenni() {
  static const openni::Status status = [] {
    const openni::Status s = openni::OpenNI::initialize();
    const openni::Version v = openni::OpenNI::getVersion();
    if (s == openni::STATUS_OK)
      spdlog::info("openni: OpenNI2 {}.{}.{}.{} initialised", v.major, v.minor, v.maintenance,
                   v.build);
    return s;
  }();
  if (status == openni::STATUS_OK) return {};
  return Status::error("OpenNI2 did not initialise: " + openniError());
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

class OpenniSource : public DepthSource,
                     openni::OpenNI::DeviceConnectedListener,
                     openni::OpenNI::DeviceDisconnectedListener {
 public:
  OpenniSource(const OpenniSourceParams& params, const PinholeCamera& camera, bool file)
      : params_(params), camera_(camera), file_(file),
        backoff_(params.reconnect_min_s, params.reconnect_max_s) {
    if (!file_) {
      usb_ = std::make_unique<UsbWatch>();
      openni::OpenNI::addDeviceConnectedListener(this);
      openni::OpenNI::addDeviceDisconnectedListener(this);
    }
  }
  ~OpenniSource() override {
    close();
    if (!file_) {
      openni::OpenNI::removeDeviceConnectedListener(this);
      openni::OpenNI::removeDeviceDisconnectedListener(this);
    }
  }

  // Recordings must open at start; a sensor may come later.
  Status openRecording() { return connect(); }

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
      // A hot-plug notice cuts the wait short; otherwise the next attempt is made when due, and
      // the wait never outlasts the read timeout.
      const auto due_ms = std::chrono::ceil<std::chrono::milliseconds>(next_attempt_ -
                                                                       Clock::now()).count();
      bool arrived = appeared_.exchange(false);
      if (!arrived)
        arrived = usb_->waitForArrival(
                      static_cast<int>(std::clamp<int64_t>(due_ms, 0, kReadTimeoutMs))) ||
                  appeared_.exchange(false);
      if (!arrived && Clock::now() < next_attempt_) {
        *why = waiting_why_;
        return SourceStatus::kWaiting;
      }
      if (const Status connected = connect(); !connected.ok()) {
        const double wait_s = backoff_.next();
        next_attempt_ = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                           std::chrono::duration<double>(wait_s));
        // The attempt number makes every retry its own log line: the log shows it goes on.
        std::ostringstream text;
        text << connected.message() << "; attempt " << ++failed_attempts_ << " failed, retrying in "
             << wait_s << " s";
        waiting_why_ = *why = text.str();
        return SourceStatus::kWaiting;
      }
      backoff_.reset();
      failed_attempts_ = 0;
    }
    // Manual playback hands out the next frame on every read, so the last one is known.
    if (file_ && frames_in_file_ > 0 && last_index_ >= frames_in_file_) {
      spdlog::info("openni: recording {}: all {} frames read", params_.uri, frames_in_file_);
      close();
      return SourceStatus::kEnd;
    }
    openni::VideoStream* streams[] = {&stream_};
    int ready = -1;
    if (lost_ || openni::OpenNI::waitForAnyStream(streams, 1, &ready, kReadTimeoutMs) !=
                     openni::STATUS_OK) {
      if (file_ && secondsFrom(last_frame_) > kSilentLostS) {
        // The capture thread logs only that the source ended; why it ended early is ours to say.
        if (frames_in_file_ > 0)
          spdlog::warn("openni: recording {} stopped delivering after {} of its {} frames: it "
                       "ends here",
                       params_.uri, frames_read_, frames_in_file_);
        else
          spdlog::warn("openni: recording {} ended after {} frames; it holds no frame count "
                       "(a recorder that never finished it?)",
                       params_.uri, frames_read_);
        close();
        return SourceStatus::kEnd;
      }
      if (!file_ && (lost_ || secondsFrom(last_frame_) > kSilentLostS)) {
        *why = lost_ ? "depth sensor unplugged" : "depth sensor silent for 2 s";
        close();
        waiting_why_ = *why + ": closed, reconnecting";
        *why = waiting_why_;
        return SourceStatus::kWaiting;
      }
      *why = "no frame within 100 ms";
      return SourceStatus::kWaiting;
    }
    if (stream_.readFrame(&frame_) != openni::STATUS_OK) {
      *why = "OpenNI2 could not read a frame: " + openniError();
      return SourceStatus::kSkipped;
    }
    ++frames_read_;
    last_index_ = frame_.getFrameIndex();
    last_frame_ = Clock::now();
    return copyFrame(out, why);
  }

 private:
  // Both called on OpenNI2's own threads (its drivers').
  void onDeviceConnected(const openni::DeviceInfo* info) override {
    if (!connected_ && (params_.uri.empty() || params_.uri == info->getUri())) appeared_ = true;
  }
  void onDeviceDisconnected(const openni::DeviceInfo* info) override {
    const std::lock_guard<std::mutex> lock(uri_mutex_);
    if (connected_ && uri_ == info->getUri()) lost_ = true;
  }

  Status connect() {
    std::string uri = params_.uri;
    if (uri.empty()) {
      openni::Array<openni::DeviceInfo> devices;
      openni::OpenNI::enumerateDevices(&devices);
      if (devices.getSize() == 0) {
        return Status::error("no depth sensor: OpenNI2 lists none (supported sensors on USB: " +
                             usb_->attached() + ")");
      }
      uri = devices[0].getUri();
    }
    if (device_.open(uri.c_str()) != openni::STATUS_OK) {
      std::string why = (file_ ? "cannot open recording " : "cannot open depth sensor ") + uri +
                        ": " + openniError();
      if (usb_) why += " (supported sensors on USB: " + usb_->attached() + ")";
      return Status::error(why);
    }
    if (const Status started = startDepth(); !started.ok()) {
      device_.close();
      return Status::error(uri + ": " + started.message());
    }
    if (file_) {
      frames_in_file_ = device_.getPlaybackControl()->getNumberOfFrames(stream_);
      frames_read_ = last_index_ = 0;
      // With a frame count the reader stops by itself, and the file driver may go round: at
      // its end it then waits for the next read instead of spinning over its list of streams,
      // which it walks unlocked while destroying a stream changes it (a crash when the two
      // meet, seen under load; OpenNI2's PlayerDevice::MainLoop and destroyStream).
      if (frames_in_file_ > 0) device_.getPlaybackControl()->setRepeatEnabled(true);
    }
    {
      const std::lock_guard<std::mutex> lock(uri_mutex_);
      uri_ = uri;
      connected_ = true;
    }
    lost_ = false;
    have_time_origin_ = false;
    last_frame_ = Clock::now();
    ++connects_;
    spdlog::info("openni: {} streaming {}x{} depth (connection {})", uri, camera_.width,
                 camera_.height, connects_);
    return {};
  }

  // Picks the configured size in millimetres, starts the stream.
  Status startDepth() {
    if (file_) {
      openni::PlaybackControl* playback = device_.getPlaybackControl();
      playback->setRepeatEnabled(false);
      // Manual: one frame each time the reader asks, every frame exactly once (0, "fastest",
      // overwrites frames the reader has not taken yet). The capture thread does the pacing.
      playback->setSpeed(-1.0f);
    }
    const openni::SensorInfo* info = device_.getSensorInfo(openni::SENSOR_DEPTH);
    if (info == nullptr) return Status::error("has no depth sensor");
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
      return Status::error("offers no " + std::to_string(camera_.width) + "x" +
                           std::to_string(camera_.height) + " millimetre depth mode " +
                           "(source.width, source.height); it offers " + offered.str());
    if (stream_.create(device_, openni::SENSOR_DEPTH) != openni::STATUS_OK)
      return Status::error("cannot create the depth stream: " + openniError());
    // Recordings replay the mode they were made with; drivers without the properties (OpenNI2's
    // test device) refuse these calls, which changes nothing.
    if (!file_) {
      stream_.setVideoMode(modes[best]);
      stream_.setMirroringEnabled(false);  // the optical frame has x to the right
    }
    if (stream_.start() != openni::STATUS_OK) {
      Status failed = Status::error("cannot start the depth stream: " + openniError());
      stream_.destroy();
      return failed;
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
    {
      const std::lock_guard<std::mutex> lock(uri_mutex_);
      connected_ = false;
    }
    frame_.release();  // the frame belongs to the stream's driver: hand it back first
    stream_.stop();
    // Some drivers (OpenNI2's test device) stop their frame thread without joining it; give it
    // a frame period to finish before the stream goes away.
    std::this_thread::sleep_for(100ms);
    stream_.destroy();
    device_.close();
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
  int64_t failed_attempts_ = 0;  // since the last connection
  std::string waiting_why_;
  openni::Device device_;
  openni::VideoStream stream_;
  openni::VideoFrameRef frame_;
  // The device's URI and whether it is open, read by OpenNI2's hot-plug thread.
  std::mutex uri_mutex_;
  std::string uri_;
  std::atomic<bool> connected_{false};
  std::atomic<bool> lost_{false};      // set by OpenNI2's hot-plug thread
  std::atomic<bool> appeared_{false};  // so is this: the sensor (or, for "", any) came back
  Clock::time_point last_frame_{};
  int64_t connects_ = 0;
  // Recordings: frames in the file (0 when it does not say), read so far, last frame number
  // (1 to frames_in_file_).
  int frames_in_file_ = 0, frames_read_ = 0, last_index_ = 0;
  bool have_time_origin_ = false;
  int64_t time_offset_us_ = 0, last_device_us_ = 0;
};

}  // namespace

Status OpenniSourceParams::validate() const {
  return firstError(checkSourceSize(width_px, height_px),
                      outOfRange("source.reconnect_min_s", reconnect_min_s, 0.01, 60),
                      outOfRange("source.reconnect_max_s", reconnect_max_s, reconnect_min_s, 600));
}

StatusOr<std::unique_ptr<DepthSource>> openOpenniSource(const OpenniSourceParams& params) {
  if (Status valid = params.validate(); !valid.ok()) return valid;
  StatusOr<PinholeCamera> camera =
      sourceCamera(kPrimeSenseFxAt640, params.width_px, params.height_px, params.intrinsics);
  if (!camera.ok()) return camera.status();
  if (Status initialised = initialiseOpenni(); !initialised.ok()) return initialised;
  std::error_code error;  // the non-throwing overloads: a bad path is a message, not an abort
  const bool file = std::filesystem::is_regular_file(params.uri, error);
  if (!file && params.uri.size() > 4 && params.uri.compare(params.uri.size() - 4, 4, ".oni") == 0)
    return Status::error("source.path: recording " + params.uri + " does not exist");
  if (std::filesystem::is_directory(params.uri, error))
    return Status::error("source.path: " + params.uri +
                         " is a folder, not a device URI or an .oni recording");
  auto source = std::make_unique<OpenniSource>(params, *camera, file);
  if (file)
    if (Status opened = source->openRecording(); !opened.ok()) return opened;
  return source;
}

}  // namespace kinfly::fw
