#include "kinfly/actuators/mavlink_port.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netdb.h>
#include <poll.h>
#include <termios.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <utility>

namespace kinfly::actuators {
namespace {

constexpr int kSerialWriteWaitMs = 5;

Status urlError(const std::string& url, const std::string& what) {
  return Status::error("MAVLink URL \"" + url + "\": " + what +
                       " (udpin:HOST:PORT, udpout:HOST:PORT or a serial device's absolute path)");
}

struct HostPort {
  std::string host;
  std::string port;
};

StatusOr<HostPort> splitHostPort(const std::string& url, const std::string& rest) {
  const size_t colon = rest.rfind(':');
  if (colon == std::string::npos || colon == 0 || colon + 1 == rest.size())
    return urlError(url, "needs HOST:PORT");
  HostPort hp{rest.substr(0, colon), rest.substr(colon + 1)};
  char* end = nullptr;
  const long port = std::strtol(hp.port.c_str(), &end, 10);
  if (*end != '\0' || port < 1 || port > 65535)
    return urlError(url, "port must be 1 to 65535, got \"" + hp.port + "\"");
  return hp;
}

speed_t baudConstant(int baud) {
  switch (baud) {
    case 9600: return B9600;
    case 19200: return B19200;
    case 38400: return B38400;
    case 57600: return B57600;
    case 115200: return B115200;
    case 230400: return B230400;
    case 460800: return B460800;
    case 500000: return B500000;
    case 921600: return B921600;
    case 1000000: return B1000000;
    case 1500000: return B1500000;
    case 2000000: return B2000000;
    case 3000000: return B3000000;
    default: return B0;
  }
}

}  // namespace

Status MavlinkPort::checkUrl(const std::string& url) {
  if (url.rfind('/', 0) == 0) return {};
  for (const char* scheme : {"udpin:", "udpout:"}) {
    if (url.rfind(scheme, 0) == 0) {
      const auto hp = splitHostPort(url, url.substr(std::strlen(scheme)));
      return hp.ok() ? Status() : hp.status();
    }
  }
  return urlError(url, "unknown form");
}

StatusOr<std::unique_ptr<MavlinkPort>> MavlinkPort::open(const std::string& url, int baud) {
  if (Status form = checkUrl(url); !form.ok()) return form;
  if (url.rfind('/', 0) == 0) {
    const speed_t speed = baudConstant(baud);
    if (speed == B0) return urlError(url, "unsupported baud rate " + std::to_string(baud));
    const int fd = ::open(url.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
    if (fd < 0) return urlError(url, std::string("cannot open the device: ") + std::strerror(errno));
    termios tio{};
    if (tcgetattr(fd, &tio) != 0) {
      const int err = errno;
      ::close(fd);
      return urlError(url, std::string("not a serial port: ") + std::strerror(err));
    }
    cfmakeraw(&tio);
    tio.c_cflag |= CLOCAL | CREAD;
    tio.c_cflag &= ~CRTSCTS;
    cfsetispeed(&tio, speed);
    cfsetospeed(&tio, speed);
    if (tcsetattr(fd, TCSANOW, &tio) != 0) {
      const int err = errno;
      ::close(fd);
      return urlError(url, std::string("cannot set the baud rate: ") + std::strerror(err));
    }
    return std::unique_ptr<MavlinkPort>(new MavlinkPort(Kind::kSerial, fd, url));
  }

  const bool in = url.rfind("udpin:", 0) == 0;
  const auto hp = splitHostPort(url, url.substr(in ? 6 : 7));
  addrinfo hints{};
  hints.ai_family = AF_INET;
  hints.ai_socktype = SOCK_DGRAM;
  hints.ai_flags = in ? AI_PASSIVE : 0;
  addrinfo* found = nullptr;
  if (const int err = getaddrinfo(hp->host.c_str(), hp->port.c_str(), &hints, &found); err != 0)
    return urlError(url, std::string("cannot resolve \"") + hp->host + "\": " + gai_strerror(err));
  const int fd = socket(AF_INET, SOCK_DGRAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  if (fd < 0) {
    freeaddrinfo(found);
    return urlError(url, std::string("socket: ") + std::strerror(errno));
  }
  auto port = std::unique_ptr<MavlinkPort>(new MavlinkPort(in ? Kind::kUdpIn : Kind::kUdpOut,
                                                           fd, url));
  if (in) {
    const int one = 1;
    setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof(one));
    if (bind(fd, found->ai_addr, found->ai_addrlen) != 0) {
      const int err = errno;
      freeaddrinfo(found);
      return urlError(url, std::string("cannot listen: ") + std::strerror(err));
    }
  } else {
    std::memcpy(&port->peer_, found->ai_addr, found->ai_addrlen);
    port->peer_len_ = found->ai_addrlen;
  }
  freeaddrinfo(found);
  return port;
}

MavlinkPort::MavlinkPort(Kind kind, int fd, std::string url)
    : kind_(kind), fd_(fd), url_(std::move(url)) {}

MavlinkPort::~MavlinkPort() { ::close(fd_); }

ssize_t MavlinkPort::read(uint8_t* data, size_t size, int timeout_ms) {
  pollfd pfd{fd_, POLLIN, 0};
  const int ready = ::poll(&pfd, 1, timeout_ms);
  if (ready <= 0) return ready < 0 && errno != EINTR ? -1 : 0;
  if (kind_ == Kind::kSerial) {
    // An unplugged USB serial port reports POLLHUP/POLLERR, or readable with 0 bytes.
    if ((pfd.revents & (POLLERR | POLLHUP | POLLNVAL)) != 0) return -1;
    const ssize_t n = ::read(fd_, data, size);
    if (n == 0) return -1;
    return n < 0 ? (errno == EAGAIN || errno == EINTR ? 0 : -1) : n;
  }
  sockaddr_storage from{};
  socklen_t from_len = sizeof(from);
  const ssize_t n =
      recvfrom(fd_, data, size, 0, reinterpret_cast<sockaddr*>(&from), &from_len);
  if (n < 0) return errno == EAGAIN || errno == EINTR ? 0 : -1;
  last_from_ = from;
  last_from_len_ = from_len;
  return n;
}

void MavlinkPort::keepPeer() {
  if (kind_ != Kind::kUdpIn || last_from_len_ == 0) return;
  peer_ = last_from_;
  peer_len_ = last_from_len_;
}

bool MavlinkPort::write(const uint8_t* data, size_t size) {
  if (kind_ == Kind::kSerial) {
    // A frame goes out whole or the link is failing: half a frame would corrupt the next one
    // too, so a full buffer is waited on briefly (a 921600 baud UART drains 90 bytes a ms).
    size_t done = 0;
    while (done < size) {
      const ssize_t n = ::write(fd_, data + done, size - done);
      if (n > 0) {
        done += static_cast<size_t>(n);
        continue;
      }
      if (n < 0 && errno != EAGAIN && errno != EINTR) return false;
      pollfd pfd{fd_, POLLOUT, 0};
      if (::poll(&pfd, 1, kSerialWriteWaitMs) <= 0) return false;
    }
    return true;
  }
  if (peer_len_ == 0) return false;
  return sendto(fd_, data, size, 0, reinterpret_cast<const sockaddr*>(&peer_), peer_len_) ==
         static_cast<ssize_t>(size);
}

}  // namespace kinfly::actuators
