"""Machine and power stage of the bike testbed: physics kernels (no ROS) and the plant node"""
