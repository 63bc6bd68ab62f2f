"""Fast DDS set-up for large depth images between processes on one machine.

With Fast DDS's built-in transports, most 1280 x 720 16UC1 frames (1.8 MB) sent at 30 Hz with
the sensor-data QoS (best effort) never arrive: measured with `make bench-node`, 62 % of 601
frames reached the segmenter. The shipped profile `config/fastdds_large_frames.xml` gives the
shared-memory transport a 32 MB segment (UDP stays for the rest): 601 of 601 arrived, with the
same node latency. Fast DDS reads a profile file named by an environment variable, so every
process of the pipeline (camera driver or bin_replay, segmenter) must start with it set:

    share=$(ros2 pkg prefix inseggan_ros)/share/inseggan_ros
    export FASTRTPS_DEFAULT_PROFILES_FILE=$share/config/fastdds_large_frames.xml

The demo and the node benchmark set it for the processes they start, unless it is set already.
Discovery is unchanged: with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST no multicast group is
joined (checked in /proc/net/igmp).
"""
from __future__ import annotations

import os
from pathlib import Path

PROFILE = "fastdds_large_frames.xml"
# Fast DDS 2.x (ROS 2 Jazzy) reads the first, Fast DDS 3.x the second.
PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


def large_frames_profile() -> Path:
    """The installed profile (share/inseggan_ros/config), else the source tree's."""
    try:
        from ament_index_python.packages import get_package_share_directory

        installed = Path(get_package_share_directory("inseggan_ros")) / "config" / PROFILE
        if installed.is_file():
            return installed
    except Exception:  # not installed through ament
        pass
    return Path(__file__).resolve().parents[2] / "config" / PROFILE


def use_large_frames_profile(environ=os.environ) -> str:
    """Point Fast DDS at the shipped profile unless a profile is set already (call before rclpy
    starts; child processes inherit it). -> the profile file in effect."""
    for v in PROFILE_VARIABLES:
        if environ.get(v):
            return environ[v]
    path = str(large_frames_profile())
    for v in PROFILE_VARIABLES:
        environ[v] = path
    return path
