"""Builders and checks shared by the test modules.

Here live the builders of on-disk layouts and recordings (derived-npy roots, UG2 folders, ROS 1 bags, in-memory
recordings), the comparison helpers for recordings, the original authors' checkpoint layouts and the location of
the real MMAUD samples. Test modules import from here and never from each other.
"""
