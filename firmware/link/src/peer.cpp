#include "kinfly/link/peer.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <sys/socket.h>
#include <sys/uio.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <cstring>

namespace kinfly::link {
namespace {

constexpr size_t kHeaderBytes = 8;  // magic and sequence number, big-endian

std::string_view trimmed(std::string_view text) {
  const auto first = text.find_first_not_of(" \t");
  if (first == std::string_view::npos) return {};
  return text.substr(first, text.find_last_not_of(" \t") - first + 1);
}

Status parsePeer(std::string_view entry, PeerAddress* peer) {
  const std::string quoted = "\"" + std::string(entry) + "\"";
  const size_t colon = entry.rfind(':');
  if (colon == std::string_view::npos || colon == 0)
    return Status::error("peer " + quoted + " is not ADDRESS:PORT");
  const std::string_view port = entry.substr(colon + 1);
  unsigned value = 0;
  const auto [end, error] = std::from_chars(port.data(), port.data() + port.size(), value);
  if (port.empty() || error != std::errc() || end != port.data() + port.size() || value == 0 ||
      value > 65535)
    return Status::error("peer " + quoted + ": the port must be a number in [1, 65535]");
  peer->host = std::string(entry.substr(0, colon));
  in_addr address{};
  if (inet_pton(AF_INET, peer->host.c_str(), &address) != 1)
    return Status::error("peer " + quoted + ": \"" + peer->host + "\" is not an IPv4 address");
  peer->port = static_cast<uint16_t>(value);
  return Status();
}

}  // namespace

Status parsePeers(std::string_view text, std::vector<PeerAddress>* peers) {
  peers->clear();
  if (trimmed(text).empty()) return Status();
  while (true) {
    const size_t comma = text.find(',');
    PeerAddress peer;
    if (Status status = parsePeer(trimmed(text.substr(0, comma)), &peer); !status.ok())
      return status;
    peers->push_back(std::move(peer));
    if (comma == std::string_view::npos) return Status();
    text.remove_prefix(comma + 1);
  }
}

PeerLink::PeerLink(std::vector<PeerAddress> peers, uint16_t listen_port, ChannelFilter accept,
                   int receive_buffer_bytes)
    : peers_(std::move(peers)), listen_port_(listen_port), accept_(std::move(accept)),
      receive_buffer_bytes_(receive_buffer_bytes) {}

PeerLink::~PeerLink() {
  if (fd_ >= 0) close(fd_);
}

Status PeerLink::open() {
  if (fd_ >= 0) return Status();
  std::vector<sockaddr_in> resolved;
  for (const PeerAddress& peer : peers_) {
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_port = htons(peer.port);
    if (inet_pton(AF_INET, peer.host.c_str(), &address.sin_addr) != 1)
      return Status::error("peer \"" + peer.host + "\" is not an IPv4 address");
    resolved.push_back(address);
  }
  const int fd = socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
  if (fd < 0) return Status::error(std::string("socket: ") + std::strerror(errno));
  // Best effort, as LCM's own recv_buf_size: the kernel caps it at net.core.rmem_max.
  if (receive_buffer_bytes_ > 0)
    setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &receive_buffer_bytes_, sizeof receive_buffer_bytes_);
  sockaddr_in local{};
  local.sin_family = AF_INET;
  local.sin_addr.s_addr = htonl(INADDR_ANY);
  local.sin_port = htons(listen_port_);
  socklen_t length = sizeof local;
  if (bind(fd, reinterpret_cast<const sockaddr*>(&local), sizeof local) != 0 ||
      getsockname(fd, reinterpret_cast<sockaddr*>(&local), &length) != 0) {
    const std::string error = std::strerror(errno);
    close(fd);
    return Status::error("cannot listen on UDP port " + std::to_string(listen_port_) + ": " +
                         error);
  }
  fd_ = fd;
  bound_port_ = ntohs(local.sin_port);
  resolved_ = std::move(resolved);
  return Status();
}

bool PeerLink::send(const std::string& channel, const uint8_t* data, size_t size) {
  if (fd_ < 0) {
    ++counters_.send_failed;
    last_send_error_ = ENOTCONN;
    return false;
  }
  if (kHeaderBytes + channel.size() + 1 + size > kMaxDatagramBytes) {
    ++counters_.too_large;
    last_send_error_ = EMSGSIZE;
    return false;
  }
  const uint32_t header[2] = {htonl(kMagic), htonl(sequence_++)};
  // The channel with its NUL, and the payload, straight from the caller's buffers.
  iovec parts[3] = {{const_cast<uint32_t*>(header), kHeaderBytes},
                    {const_cast<char*>(channel.c_str()), channel.size() + 1},
                    {const_cast<uint8_t*>(data), size}};
  bool any = false;
  for (sockaddr_in& to : resolved_) {
    msghdr message{};
    message.msg_name = &to;
    message.msg_namelen = sizeof to;
    message.msg_iov = parts;
    message.msg_iovlen = 3;
    if (sendmsg(fd_, &message, MSG_DONTWAIT) >= 0) {
      ++counters_.sent;
      any = true;
    } else {
      ++counters_.send_failed;
      last_send_error_ = errno;
    }
  }
  return any;
}

int PeerLink::receive(const Handler& handler) {
  int handed = 0;
  for (int datagrams = 0; fd_ >= 0 && datagrams < kMaxReceivePerCall; ++datagrams) {
    sockaddr_in from{};
    socklen_t length = sizeof from;
    const ssize_t got = recvfrom(fd_, datagram_.data(), datagram_.size(), MSG_DONTWAIT,
                                 reinterpret_cast<sockaddr*>(&from), &length);
    if (got < 0) break;  // nothing more waiting (EAGAIN), or an error the next poll reports
    if (!fromPeer(from)) {
      ++counters_.foreign;
      continue;
    }
    const auto size = static_cast<size_t>(got);
    uint32_t magic = 0;
    if (size >= kHeaderBytes) std::memcpy(&magic, datagram_.data(), sizeof magic);
    const auto* channel = reinterpret_cast<const char*>(datagram_.data() + kHeaderBytes);
    const size_t room = size >= kHeaderBytes ? size - kHeaderBytes : 0;
    const size_t channel_bytes = strnlen(channel, std::min(room, kMaxChannelBytes + 1));
    if (ntohl(magic) != kMagic || channel_bytes == 0 || channel_bytes > kMaxChannelBytes ||
        channel_bytes == room) {
      ++counters_.malformed;
      continue;
    }
    if (!accept_(std::string_view(channel, channel_bytes))) {
      ++counters_.unexpected_channel;
      continue;
    }
    ++counters_.received;
    ++handed;
    const size_t offset = kHeaderBytes + channel_bytes + 1;
    handler(channel, datagram_.data() + offset, size - offset);
  }
  return handed;
}

bool PeerLink::fromPeer(const sockaddr_in& from) const {
  return std::any_of(resolved_.begin(), resolved_.end(), [&](const sockaddr_in& peer) {
    return peer.sin_addr.s_addr == from.sin_addr.s_addr;
  });
}

}  // namespace kinfly::link
