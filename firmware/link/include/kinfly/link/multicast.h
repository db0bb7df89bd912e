// Whether LCM's UDP multicast can start: LCM refuses to without a route to its group, and prints
// a page of advice on every attempt. The drone asks first, so that it can wait for a Wi-Fi that
// is not up yet with one log line of its own.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "kinfly/core/status.h"

namespace kinfly::link {

struct MulticastTarget {
  std::string group;  // dotted IPv4 address
  uint16_t port = 0;
  int ttl = 0;        // LCM's default: nothing leaves the machine
};

// LCM's URL when none is given and LCM_DEFAULT_URL is not set.
inline constexpr const char* kLcmDefaultUrl = "udpm://239.255.76.67:7667?ttl=0";

// The URL LCM uses for `lcm_url`: itself, or for "" LCM_DEFAULT_URL if set, else kLcmDefaultUrl.
std::string resolvedLcmUrl(const std::string& lcm_url);

// The multicast group and port LCM would use for `lcm_url` ("" means LCM_DEFAULT_URL, else
// LCM's default); nullopt for providers that need no network (memq://, file://).
std::optional<MulticastTarget> multicastTarget(const std::string& lcm_url);

// Ok when the target is an IPv4 multicast group and a port, else what is wrong with it: a
// configuration error, unlike a missing route.
Status checkMulticastTarget(const MulticastTarget& target);

// Ok when the kernel has a route to the target, else why not (as connect() says it).
Status checkMulticastRoute(const MulticastTarget& target);

}  // namespace kinfly::link
