"""Robot-ready outputs: the camera in the robot's frame (handeye), pick-and-place gripper targets (targets)
and ROS 2 messages in MCAP (ros2)."""
