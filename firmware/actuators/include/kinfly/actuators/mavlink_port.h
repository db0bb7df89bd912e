// The byte stream to an autopilot, as the ground's MAVLink bridge names it (docs/mavlink.md):
//   udpin:HOST:PORT   listen on HOST:PORT; replies go to the autopilot's address, the sender of
//                     the last datagram its owner vouched for (keepPeer)
//   udpout:HOST:PORT  send to HOST:PORT (the autopilot listens), from an ephemeral port
//   /dev/...          a serial device (a flight controller's TELEM or USB port), at `baud`: any
//                     absolute path, so that udev's stable names (/dev/serial/by-id/...) do
// Non-blocking underneath; read() waits at most its timeout.
#pragma once

#include <sys/socket.h>
#include <sys/types.h>

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>

#include "kinfly/core/status.h"

namespace kinfly::actuators {

class MavlinkPort {
 public:
  // An error names the URL and what is wrong with it (form, host, port, device, baud).
  static StatusOr<std::unique_ptr<MavlinkPort>> open(const std::string& url, int baud);
  // Only the URL's form, for configuration checks before anything is opened.
  static Status checkUrl(const std::string& url);
  ~MavlinkPort();
  MavlinkPort(const MavlinkPort&) = delete;
  MavlinkPort& operator=(const MavlinkPort&) = delete;

  // Waits up to timeout_ms for bytes and reads what there is, at most `size`: the count, 0 for
  // none, -1 on an error of the device (the serial port unplugged).
  ssize_t read(uint8_t* data, size_t size, int timeout_ms);
  // False when nothing could be sent: a udpin port that has no peer yet, or the kernel refused
  // (a full buffer, no route).
  bool write(const uint8_t* data, size_t size);
  // udpin: the sender of the datagram read last becomes the peer. Called only for a frame that
  // passed its signature and came from the autopilot, so that anyone else on the network who
  // sends a datagram cannot turn our setpoints towards themselves.
  void keepPeer();
  const std::string& url() const { return url_; }

 private:
  enum class Kind { kUdpIn, kUdpOut, kSerial };
  MavlinkPort(Kind kind, int fd, std::string url);

  Kind kind_;
  int fd_;
  std::string url_;
  // UDP: where writes go (udpout: the URL's; udpin: the last sender's).
  sockaddr_storage peer_{};
  socklen_t peer_len_ = 0;  // 0: no peer yet
  sockaddr_storage last_from_{};
  socklen_t last_from_len_ = 0;
};

}  // namespace kinfly::actuators
