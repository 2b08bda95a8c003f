"""Frame sources of the robot daemon: each kind of source (synthetic, photo, video, camera, bag,
ROS 2, Zenoh), opened from a spec of the source grammar (`common.source_spec`)."""
