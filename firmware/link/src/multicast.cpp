#include "kinfly/link/multicast.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>

namespace kinfly::link {

std::string resolvedLcmUrl(const std::string& lcm_url) {
  if (!lcm_url.empty()) return lcm_url;
  const char* env = std::getenv("LCM_DEFAULT_URL");
  return env != nullptr && *env != '\0' ? env : kLcmDefaultUrl;
}

std::optional<MulticastTarget> multicastTarget(const std::string& lcm_url) {
  const std::string url = resolvedLcmUrl(lcm_url);
  const std::string scheme = "udpm://";
  if (url.compare(0, scheme.size(), scheme) != 0) return std::nullopt;
  // udpm://GROUP:PORT?options, where LCM fills in whichever of GROUP and PORT is missing.
  std::string address = url.substr(scheme.size());
  const size_t query = address.find('?');
  MulticastTarget target{"239.255.76.67", 7667, 0};
  if (query != std::string::npos) {
    const std::string options = "&" + address.substr(query + 1);
    if (const size_t ttl = options.find("&ttl="); ttl != std::string::npos)
      target.ttl = std::atoi(options.c_str() + ttl + 5);
  }
  address = address.substr(0, query);
  const size_t colon = address.find(':');
  if (!address.empty() && colon != 0) target.group = address.substr(0, colon);
  if (colon != std::string::npos && colon + 1 < address.size())
    target.port = static_cast<uint16_t>(std::atoi(address.c_str() + colon + 1));
  return target;
}

Status checkMulticastTarget(const MulticastTarget& target) {
  in_addr address{};
  if (inet_pton(AF_INET, target.group.c_str(), &address) != 1)
    return Status::error("\"" + target.group + "\" is not an IPv4 address");
  if (!IN_MULTICAST(ntohl(address.s_addr)))
    return Status::error(target.group +
                         " is not a multicast group (224.0.0.0 to 239.255.255.255)");
  if (target.port == 0) return Status::error("the port must be in [1, 65535]");
  return Status();
}

Status checkMulticastRoute(const MulticastTarget& target) {
  sockaddr_in to{};
  to.sin_family = AF_INET;
  to.sin_port = htons(target.port);
  if (Status valid = checkMulticastTarget(target); !valid.ok()) return valid;
  inet_pton(AF_INET, target.group.c_str(), &to.sin_addr);
  const int fd = socket(AF_INET, SOCK_DGRAM, 0);
  if (fd < 0) return Status::error(std::string("socket: ") + std::strerror(errno));
  // A UDP connect() sends nothing: it only looks up the route, as LCM does before it starts.
  const int connected = connect(fd, reinterpret_cast<const sockaddr*>(&to), sizeof to);
  const int error = errno;
  close(fd);
  if (connected == 0) return Status();
  return Status::error("no route to the multicast group " + target.group + " (" +
                       std::strerror(error) + ")");
}

}  // namespace kinfly::link
