// The unicast link (firmware/link peer.h): peers parsed with errors that name the entry, LCM's
// small-message packet on the wire, and only the peers' hosts and the owner's channels taken.
#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cstring>
#include <string>
#include <vector>

#include "kinfly/link/channels.h"
#include "kinfly/link/peer.h"

namespace kinfly::link {
namespace {

constexpr int kVehicle = 7;
constexpr int kWaitMs = 5000;  // a datagram on loopback arrives at once; this is only a bound

// A plain UDP socket on a loopback address, to send what a PeerLink would not (or from another
// host) and to see the bytes a PeerLink sends.
class RawSocket {
 public:
  explicit RawSocket(const char* address) {
    fd_ = socket(AF_INET, SOCK_DGRAM, 0);
    sockaddr_in local{};
    local.sin_family = AF_INET;
    inet_pton(AF_INET, address, &local.sin_addr);
    socklen_t length = sizeof local;
    EXPECT_EQ(bind(fd_, reinterpret_cast<sockaddr*>(&local), sizeof local), 0);
    getsockname(fd_, reinterpret_cast<sockaddr*>(&local), &length);
    port_ = ntohs(local.sin_port);
  }
  ~RawSocket() { close(fd_); }
  uint16_t port() const { return port_; }
  void sendTo(uint16_t port, const std::vector<uint8_t>& bytes) const {
    sockaddr_in to{};
    to.sin_family = AF_INET;
    to.sin_port = htons(port);
    inet_pton(AF_INET, "127.0.0.1", &to.sin_addr);
    ASSERT_EQ(sendto(fd_, bytes.data(), bytes.size(), 0, reinterpret_cast<sockaddr*>(&to),
                     sizeof to),
              static_cast<ssize_t>(bytes.size()));
  }
  std::vector<uint8_t> receive() const {
    pollfd ready{fd_, POLLIN, 0};
    EXPECT_EQ(poll(&ready, 1, kWaitMs), 1);
    std::vector<uint8_t> bytes(PeerLink::kMaxDatagramBytes);
    const ssize_t got = recv(fd_, bytes.data(), bytes.size(), MSG_DONTWAIT);
    bytes.resize(got > 0 ? static_cast<size_t>(got) : 0);
    return bytes;
  }

 private:
  int fd_ = -1;
  uint16_t port_ = 0;
};

std::vector<uint8_t> lcmPacket(uint32_t magic, const std::string& channel,
                               const std::vector<uint8_t>& payload, bool terminate = true) {
  const uint32_t header[2] = {htonl(magic), htonl(41)};
  std::string bytes(sizeof header, '\0');
  std::memcpy(bytes.data(), header, sizeof header);
  bytes += channel;
  if (terminate) bytes.push_back('\0');
  bytes.append(payload.begin(), payload.end());
  return {bytes.begin(), bytes.end()};
}

struct Received {
  std::string channel;
  std::vector<uint8_t> data;
};

// Waits for the socket, then takes what is there.
std::vector<Received> receiveAll(PeerLink* link) {
  pollfd ready{link->fd(), POLLIN, 0};
  EXPECT_EQ(poll(&ready, 1, kWaitMs), 1);
  std::vector<Received> all;
  link->receive([&](const char* channel, const uint8_t* data, size_t size) {
    all.push_back({channel, std::vector<uint8_t>(data, data + size)});
  });
  return all;
}

// The drone's end: this vehicle's channels that the ground sends.
PeerLink droneEnd(uint16_t ground_port) {
  return PeerLink({{"127.0.0.1", ground_port}}, 0, [](std::string_view channel) {
    const auto parsed = parseChannel(channel);
    return parsed && parsed->vehicle_id == kVehicle && sentByGround(parsed->channel);
  });
}

TEST(Peers, ParseAListAndNameTheBadEntry) {
  std::vector<PeerAddress> peers;
  ASSERT_TRUE(parsePeers(" 192.168.4.10:7668 , 10.0.0.2:9000", &peers).ok());
  ASSERT_EQ(peers.size(), 2u);
  EXPECT_EQ(peers[0].host, "192.168.4.10");
  EXPECT_EQ(peers[0].port, 7668);
  EXPECT_EQ(peers[1].host, "10.0.0.2");
  EXPECT_EQ(peers[1].port, 9000);
  ASSERT_TRUE(parsePeers("  ", &peers).ok());
  EXPECT_TRUE(peers.empty());
  // Names are refused: resolving one blocks the sending threads while the Wi-Fi comes up.
  for (const char* bad : {"ground", "ground:", ":7668", "10.0.0.2:0", "10.0.0.2:65536",
                          "10.0.0.2:76x8", "10.0.0.2:1,,10.0.0.3:2", "10.0.0.2:1,",
                          "ground.local:7668", "fe80::1:7668", "10.0.0.256:7668"}) {
    const Status status = parsePeers(bad, &peers);
    EXPECT_FALSE(status.ok()) << bad;
    EXPECT_NE(status.message().find("peer \""), std::string::npos) << status.message();
  }
}

TEST(Peers, SendsLcmSmallMessagePacketsToEveryPeer) {
  RawSocket first("127.0.0.1"), second("127.0.0.1");
  PeerLink link({{"127.0.0.1", first.port()}, {"127.0.0.1", second.port()}}, 0,
                [](std::string_view) { return true; });
  ASSERT_TRUE(link.open().ok());
  const std::string channel = channelName(Channel::kKeyframeChunk, kVehicle);
  const std::vector<uint8_t> payload = {1, 2, 3, 0, 255};
  for (int i = 0; i < 2; ++i) ASSERT_TRUE(link.send(channel, payload.data(), payload.size()));
  EXPECT_EQ(link.counters().sent, 4);
  for (const RawSocket* peer : {&first, &second}) {
    for (uint32_t sequence = 0; sequence < 2; ++sequence) {
      const std::vector<uint8_t> bytes = peer->receive();
      // LCM's own packet ("LC02", sequence, channel, NUL, payload): each peer's sequence is the
      // link's message count, as LCM numbers what one publisher sends.
      std::vector<uint8_t> expected = lcmPacket(PeerLink::kMagic, channel, payload);
      const uint32_t expected_sequence = htonl(sequence);
      std::memcpy(expected.data() + 4, &expected_sequence, 4);
      EXPECT_EQ(bytes, expected);
    }
  }
}

TEST(Peers, TakeOnlyTheOwnersChannelsFromThePeersHosts) {
  PeerLink drone = droneEnd(/*ground_port=*/9);
  ASSERT_TRUE(drone.open().ok());
  PeerLink sender({{"127.0.0.1", drone.listenPort()}}, 0, [](std::string_view) { return true; });
  ASSERT_TRUE(sender.open().ok());

  const std::vector<uint8_t> correction = {9, 8, 7};
  ASSERT_TRUE(sender.send(channelName(Channel::kCorrection, kVehicle), correction.data(),
                          correction.size()));
  std::vector<Received> got = receiveAll(&drone);
  ASSERT_EQ(got.size(), 1u);
  EXPECT_EQ(got[0].channel, channelName(Channel::kCorrection, kVehicle));
  EXPECT_EQ(got[0].data, correction);

  // Another vehicle's correction, and a channel the drone itself sends: not taken.
  sender.send(channelName(Channel::kCorrection, kVehicle + 1), correction.data(), 3);
  sender.send(channelName(Channel::kOdometry, kVehicle), correction.data(), 3);
  // Not LCM's packet: another magic, no NUL after the channel, an empty channel.
  RawSocket raw("127.0.0.1");
  const std::string status = channelName(Channel::kGroundStatus, kVehicle);
  raw.sendTo(drone.listenPort(), lcmPacket(0x4c433033, status, correction));
  raw.sendTo(drone.listenPort(), lcmPacket(PeerLink::kMagic, status, {}, false));
  raw.sendTo(drone.listenPort(), lcmPacket(PeerLink::kMagic, "", correction));
  raw.sendTo(drone.listenPort(), {0x4c, 0x43});
  // From a host that is not a peer (loopback has all of 127/8).
  RawSocket stranger("127.0.0.2");
  stranger.sendTo(drone.listenPort(), lcmPacket(PeerLink::kMagic, status, correction));
  // The last one, from the peer, marks that all before it are in.
  raw.sendTo(drone.listenPort(), lcmPacket(PeerLink::kMagic, status, correction));
  got.clear();
  while (got.empty()) got = receiveAll(&drone);
  ASSERT_EQ(got.size(), 1u);
  EXPECT_EQ(got[0].channel, status);
  EXPECT_EQ(drone.counters().received, 2);
  EXPECT_EQ(drone.counters().unexpected_channel, 2);
  EXPECT_EQ(drone.counters().malformed, 4);
  EXPECT_EQ(drone.counters().foreign, 1);
}

TEST(Peers, RefuseWhatOneDatagramCannotCarryAndSendingBeforeOpen) {
  PeerLink link({{"127.0.0.1", 9}}, 0, [](std::string_view) { return true; });
  const std::vector<uint8_t> payload(PeerLink::kMaxDatagramBytes);
  EXPECT_FALSE(link.send("KINFLY_7_STATUS", payload.data(), 16));
  EXPECT_EQ(link.counters().send_failed, 1);
  ASSERT_TRUE(link.open().ok());
  EXPECT_FALSE(link.send("KINFLY_7_STATUS", payload.data(), payload.size()));
  EXPECT_EQ(link.counters().too_large, 1);
  EXPECT_EQ(link.lastSendError(), EMSGSIZE);
}

TEST(Peers, SayWhyTheyCannotOpen) {
  RawSocket taken("0.0.0.0");
  PeerLink clash({{"127.0.0.1", 7668}}, taken.port(), [](std::string_view) { return true; });
  const Status in_use = clash.open();
  EXPECT_FALSE(in_use.ok());
  EXPECT_NE(in_use.message().find(std::to_string(taken.port())), std::string::npos);
}

}  // namespace
}  // namespace kinfly::link
