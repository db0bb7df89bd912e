#include "kinfly/io/tum_dataset.h"

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iomanip>
#include <sstream>
#include <sys/stat.h>

namespace kinfly {

namespace {

bool isDirectory(const std::string& path) {
  struct stat st {};
  return ::stat(path.c_str(), &st) == 0 && S_ISDIR(st.st_mode);
}

bool isBlankOrComment(const std::string& line) {
  const size_t i = line.find_first_not_of(" \t\r");
  return i == std::string::npos || line[i] == '#';
}

std::string where(const std::string& path, int line) {
  return path + ":" + std::to_string(line) + ": ";
}

}  // namespace

Status readTumDepthList(const std::string& dir, std::vector<TumDepthEntry>* entries) {
  entries->clear();
  if (!isDirectory(dir)) return Status::error(dir + ": no such directory");
  const std::string list = dir + "/depth.txt";
  std::ifstream in(list);
  if (!in)
    return Status::error(list + ": cannot open (" + std::strerror(errno) +
                         "); a TUM folder has depth.txt");
  std::string line;
  for (int n = 1; std::getline(in, line); ++n) {
    if (isBlankOrComment(line)) continue;
    std::istringstream fields(line);
    TumDepthEntry e;
    std::string file, extra;
    if (!(fields >> e.timestamp_s >> file) || (fields >> extra) || !std::isfinite(e.timestamp_s))
      return Status::error(where(list, n) + "expected \"timestamp filename\", got \"" + line +
                           "\"");
    if (!entries->empty() && e.timestamp_s <= entries->back().timestamp_s)
      return Status::error(where(list, n) + "timestamps must increase");
    e.path = file.front() == '/' ? file : dir + "/" + file;
    entries->push_back(std::move(e));
  }
  if (entries->empty()) return Status::error(list + ": lists no depth images");
  return {};
}

Status readTumTrajectory(const std::string& path, std::vector<StampedPose>* poses) {
  poses->clear();
  std::ifstream in(path);
  if (!in) return Status::error(path + ": cannot open (" + std::strerror(errno) + ")");
  std::string line;
  for (int n = 1; std::getline(in, line); ++n) {
    if (isBlankOrComment(line)) continue;
    std::istringstream fields(line);
    StampedPose p;
    std::array<double, 7> v{};
    std::string extra;
    bool ok = static_cast<bool>(fields >> p.timestamp_s);
    for (double& x : v) ok = ok && static_cast<bool>(fields >> x);
    if (!ok || (fields >> extra))
      return Status::error(where(path, n) + "expected \"t tx ty tz qx qy qz qw\", got \"" +
                           line + "\"");
    const double qn = std::sqrt(v[3] * v[3] + v[4] * v[4] + v[5] * v[5] + v[6] * v[6]);
    if (!(std::fabs(qn - 1.0) < 1e-2))
      return Status::error(where(path, n) + "quaternion is not unit length");
    p.T_world_cam = poseFromTum(v);
    poses->push_back(p);
  }
  std::sort(poses->begin(), poses->end(),
            [](const StampedPose& a, const StampedPose& b) { return a.timestamp_s < b.timestamp_s; });
  if (poses->empty()) return Status::error(path + ": holds no poses");
  return {};
}

Status writeTumTrajectory(const std::string& path, const std::vector<StampedPose>& poses) {
  std::ofstream out(path, std::ios::trunc);
  if (!out) return Status::error("cannot write " + path + ": " + std::strerror(errno));
  out << "# timestamp tx ty tz qx qy qz qw (camera-to-world, metres)\n" << std::fixed;
  for (const StampedPose& p : poses) {
    const std::array<double, 7> v = poseToTum(p.T_world_cam);
    out << std::setprecision(6) << p.timestamp_s << std::setprecision(7);
    for (double x : v) out << ' ' << x;
    out << '\n';
  }
  out.close();
  if (!out) return Status::error("failed writing " + path);
  return {};
}

const StampedPose* findNearestPose(const std::vector<StampedPose>& poses, double t, double max_dt_s) {
  auto it = std::lower_bound(poses.begin(), poses.end(), t,
                             [](const StampedPose& p, double time) { return p.timestamp_s < time; });
  const StampedPose* best = nullptr;
  double best_dt = max_dt_s;
  for (auto c : {it, it == poses.begin() ? it : std::prev(it)}) {
    if (c == poses.end()) continue;
    const double dt = std::fabs(c->timestamp_s - t);
    if (dt <= best_dt) {
      best = &*c;
      best_dt = dt;
    }
  }
  return best;
}

}  // namespace kinfly
