"""The drone's camera service: colour, aligned depth, calibration and the camera/gripper mounts on the bus."""
