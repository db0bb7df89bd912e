# The message types in proto/kinfly/, one per .lcm file. Both code generators (C++ in
# proto/CMakeLists.txt, Python in ground/CMakeLists.txt) read this list.
set(KINFLY_LCM_TYPES
  camera_t
  chunk_request_t
  depth_keyframe_t
  drone_status_t
  flight_command_t
  flight_status_t
  ground_status_t
  ground_truth_t
  imu_t
  keyframe_chunk_t
  motor_command_t
  odometry_t
  pose3d_t
  pose_correction_t
  signed_t
  sim_state_t
)
