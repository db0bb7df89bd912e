#include "publisher.h"

namespace kinfly::fw {

Publisher::Publisher(const std::string& url, int vehicle_id) : lcm_(url) {
  for (size_t i = 0; i < channels_.size(); ++i)
    channels_[i] = link::channelName(static_cast<link::Channel>(i), vehicle_id);
}

std::unique_ptr<Publisher> Publisher::open(const std::string& url, int vehicle_id,
                                           std::string* why) {
  std::unique_ptr<Publisher> publisher(new Publisher(url, vehicle_id));
  if (!publisher->lcm_.good()) {
    *why = "cannot start LCM on \"" + url + "\" (link.lcm_url)";
    return nullptr;
  }
  return publisher;
}

}  // namespace kinfly::fw
