#include "kinfly/core/camera.h"

#include <cmath>
#include <sstream>
#include <stdexcept>
#include <vector>

namespace kinfly {

Status PinholeCamera::validate() const {
  std::ostringstream why;
  if (!(std::isfinite(fx) && fx > 0.f)) why << "fx must be a positive number (got " << fx << ")";
  else if (!(std::isfinite(fy) && fy > 0.f)) why << "fy must be a positive number (got " << fy << ")";
  else if (width <= 0 || height <= 0) why << "image size must be positive (got " << width << "x" << height << ")";
  else if (!(std::isfinite(cx) && cx >= 0.f && cx <= static_cast<float>(width)))
    why << "cx must lie inside the image width " << width << " (got " << cx << ")";
  else if (!(std::isfinite(cy) && cy >= 0.f && cy <= static_cast<float>(height)))
    why << "cy must lie inside the image height " << height << " (got " << cy << ")";
  return why.str().empty() ? Status() : Status::error(why.str());
}

PinholeCamera PinholeCamera::scaled(int factor) const {
  // Level pixel x' samples the finer pixel factor * x', so the principal point divides exactly.
  const float f = static_cast<float>(factor);
  return {fx / f, fy / f, cx / f, cy / f, width / factor, height / factor};
}

Status parseIntrinsics(const std::string& text, PinholeCamera* camera) {
  std::vector<float> v;
  std::stringstream in(text);
  std::string item;
  while (std::getline(in, item, ',')) {
    try {
      size_t used = 0;
      v.push_back(std::stof(item, &used));
      if (used != item.size()) throw std::invalid_argument(item);
    } catch (const std::exception&) {
      return Status::error("--intrinsics: \"" + item + "\" is not a number");
    }
  }
  if (v.size() != 4)
    return Status::error("--intrinsics expects 4 comma-separated numbers fx,fy,cx,cy (got \"" +
                         text + "\")");
  camera->fx = v[0];
  camera->fy = v[1];
  camera->cx = v[2];
  camera->cy = v[3];
  return {};
}

}  // namespace kinfly
