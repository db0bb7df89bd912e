# The message types in proto/kinfly/, one per .lcm file. Both code generators (C++ in
# proto/CMakeLists.txt, Python in ground/CMakeLists.txt) read this list.
set(KINFLY_LCM_TYPES
  depth_keyframe_t
  imu_t
  odometry_t
  pose_t
  pose_correction_t
  signed_t
  status_t
)
