// The unicast link (docs/wire.md, "Unicast on Wi-Fi"): LCM messages sent by UDP unicast to the
// other side's address, for a Wi-Fi where multicast hurts. An access point sends multicast at
// its basic rate and never retransmits it; unicast frames go at the station's own rate and the
// link layer acknowledges and retransmits them.
//
// LCM 1.3's providers have no peer-to-peer UDP one (udpm joins a multicast group; tcpq needs a
// relay server, and TCP would stall corrections behind keyframes), so this sends each message
// as one datagram in LCM's own small-message packet ("LC02", sequence number, channel, payload;
// readable by LCM's Wireshark dissector) to each peer, and accepts datagrams only from the
// peers' hosts and only on the channels the owner expects. The owner hands what it receives to
// the same handler its LCM subscription calls (the drone) or publishes it on its local LCM (the
// ground, so that lcm-logger records it): one receive path, whatever the transport.
//
// No thread of its own and no allocation per message: the owner polls fd() with its LCM's.
#pragma once

#include <netinet/in.h>

#include <array>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <string>
#include <string_view>
#include <vector>

#include "kinfly/core/status.h"

namespace kinfly::link {

struct PeerAddress {
  std::string host;  // dotted IPv4 address
  uint16_t port = 0;
};

// "ADDRESS:PORT[,ADDRESS:PORT...]" (spaces allowed around commas), IPv4 addresses only: a name
// would need the resolver, which blocks for seconds while the Wi-Fi comes up, on the threads
// that send (give the ground station a fixed address or a DHCP reservation). An error names the
// bad entry. Empty text: no peers (unicast off).
Status parsePeers(std::string_view text, std::vector<PeerAddress>* peers);

struct PeerCounters {
  int64_t sent = 0;         // datagrams sent, one per message and peer
  int64_t send_failed = 0;  // not sent: no route yet, the send buffer full, not open
  int64_t too_large = 0;    // messages above one datagram: not sent (chunk keyframes)
  int64_t received = 0;     // datagrams accepted and handed on
  int64_t foreign = 0;      // datagrams from a host that is not a peer: dropped
  int64_t malformed = 0;    // not an LCM small-message packet: dropped
  int64_t unexpected_channel = 0;  // a channel the owner does not take from its peers: dropped
};

class PeerLink {
 public:
  // The kinfly port for unicast when none is given (LCM's multicast port + 1).
  static constexpr uint16_t kDefaultPort = 7668;
  // LCM's small-message header: magic, sequence number; then the channel and its NUL.
  static constexpr uint32_t kMagic = 0x4c433032;  // "LC02"
  static constexpr size_t kMaxChannelBytes = 63;  // LCM's limit
  // The largest UDP payload IPv4 carries.
  static constexpr size_t kMaxDatagramBytes = 65507;

  using Handler = std::function<void(const char* channel, const uint8_t* data, size_t size)>;
  using ChannelFilter = std::function<bool(std::string_view channel)>;

  // At most this many datagrams per receive(): a flood cannot hold the owner's thread.
  static constexpr int kMaxReceivePerCall = 256;

  // Listens on listen_port (0: any free port, for a side that only sends) for datagrams from
  // the peers' hosts on channels `accept` takes; sends to every peer. receive_buffer_bytes: the
  // socket's, 0 to leave the kernel's default (a side that only sends).
  PeerLink(std::vector<PeerAddress> peers, uint16_t listen_port, ChannelFilter accept,
           int receive_buffer_bytes = 4 << 20);
  ~PeerLink();
  PeerLink(const PeerLink&) = delete;
  PeerLink& operator=(const PeerLink&) = delete;

  // Opens the socket; an error says why (a port in use). The owner retries.
  Status open();
  bool isOpen() const { return fd_ >= 0; }
  // The socket to poll for reading; -1 until open.
  int fd() const { return fd_; }
  uint16_t listenPort() const { return bound_port_; }
  size_t peerCount() const { return peers_.size(); }

  // Sends one encoded message to every peer without blocking (a full send buffer drops it);
  // false if it reached none (counted).
  bool send(const std::string& channel, const uint8_t* data, size_t size);
  // Hands the datagrams waiting on the socket (kMaxReceivePerCall at most) to `handler`,
  // without blocking; how many.
  int receive(const Handler& handler);

  const PeerCounters& counters() const { return counters_; }
  // errno of the last send that failed (EMSGSIZE: too large; ENOTCONN: not open).
  int lastSendError() const { return last_send_error_; }

 private:
  bool fromPeer(const sockaddr_in& from) const;

  std::vector<PeerAddress> peers_;
  std::vector<sockaddr_in> resolved_;
  uint16_t listen_port_ = 0, bound_port_ = 0;
  ChannelFilter accept_;
  int receive_buffer_bytes_ = 0;
  int fd_ = -1;
  uint32_t sequence_ = 0;
  int last_send_error_ = 0;
  std::array<uint8_t, kMaxDatagramBytes> datagram_{};
  PeerCounters counters_;
};

}  // namespace kinfly::link
