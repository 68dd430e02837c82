"""Torque controller of the bike testbed: control laws (no ROS) and the batched inner-loop node"""
