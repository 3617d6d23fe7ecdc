"""The ROS 2 bridge: the vehicle's camera, tf, pose, odometry, detections and reasoning steps on ROS 2 topics,
and a ROS 2 service that starts a task, in rmw_zenoh's wire format on the stack's own Zenoh router."""
