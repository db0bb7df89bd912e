// The worlds the simulated drone flies in (docs/sim.md, "Scenes"): a triangle mesh in the
// simulator's world (gravity-aligned, z down, metres), which the depth camera renders, the
// collision check tests and the fused map is scored against; its floor, on which the drone
// starts and lands; and where it starts.
#pragma once

#include <Eigen/Core>
#include <string>
#include <vector>

#include "kinfly/core/status.h"
#include "kinfly/mesh/mesh.h"

namespace kinfly::sim {

struct Scene {
  std::string name;
  // Everything the camera sees, the floor first: triangles [0, floor_triangles) are the floor,
  // which carries the drone (Multirotor's floor) and which a landing must not count as a
  // collision.
  TriangleMesh mesh;
  int floor_triangles = 0;
  double floor_z_m = 0.0;                          // [m] world height of the floor (z down)
  Eigen::Vector2d start_xy_m = Eigen::Vector2d::Zero();  // [m] where the drone stands at the start
  double start_yaw_rad = 0.0;                      // [rad] its heading there
};

// A furnished room, 6 m x 5 m x 2.7 m (x in [-3, 3], y in [-2.5, 2.5], the ceiling at
// z = -2.7): boxes, two pillars, a table, two ramps, a flight of steps, so that ICP has structure
// to hold on to from anywhere in it, the ground standing included, and every wall within the
// odometry's 4 m. The drone starts in the
// middle, heading +x.
Scene furnishedRoom();

// A corridor 30 m long, 2 m wide, 2.5 m high, featureless: its walls are planes along x, so ICP
// cannot tell motion along the corridor (the hard case). The drone starts 1 m from the closed end
// at x = -2, heading down the corridor; the far end is beyond the camera's range.
Scene corridor();

// A ring of corridors round a block, the kind of loop a drone flies round a building's floor:
// 14 m x 12 m x 2.5 m outside (x in [-7, 7], y in [-6, 6]), the block 8 m x 6 m in the middle,
// so each corridor is 3 m wide and a lap along their middles is 40 m. Partitions from the walls
// every few metres (alternate walls along the x corridors, the wall the +x camera faces along
// the y ones) and crates between them give ICP structure along each corridor. The drone
// starts in the corner at (-5.5, -4.5), heading +x down the corridor at y in [-6, -3]; a lap
// is long enough for the odometry to drift before it comes back (docs/sim.md, "Scenes").
Scene ringCorridor();
// A 7.2 m square hall, 3 m high, crates and pillars against its walls: the far wall 3.6 m off
// whichever way the drone, in its middle, looks (issue 17's far range; docs/sim.md, "Scenes").
Scene hall();

// A scene from a mesh file (PLY, OBJ, OFF or STL: readMeshFile), in metres with z up, as
// Replica's and most scans' are; a half turn about x puts it in the simulator's world (z down:
// a point (x, y, z) of the file is at (x, -y, -z)). Its floor: each 1 cm band of heights weighed
// by the horizontal faces' area within 3 cm of it, the lowest band with a quarter of the heaviest
// (a ceiling may weigh more), at its faces' mean height; every face within 3 cm of that height is
// the floor's, which carries the drone. The drone starts at start_xy_m on the floor, heading
// start_heading_rad counter-clockwise from the mesh's +x seen from above, both in the mesh's own
// frame. An error names the file.
StatusOr<Scene> loadMeshScene(const std::string& path, const Eigen::Vector2d& start_xy_m,
                              double start_heading_rad);

// The scenes by name: room, corridor, ring, hall. An error names the name and the known ones.
StatusOr<Scene> makeScene(const std::string& name);
// The names makeScene knows, for --help.
const std::vector<std::string>& sceneNames();

}  // namespace kinfly::sim
