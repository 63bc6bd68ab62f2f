"""The shipped Fast DDS profile for large frames: valid, installed, and it delivers them."""
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from inseggan_ros.ros.dds import PROFILE_VARIABLES, large_frames_profile, use_large_frames_profile

pytestmark = pytest.mark.serial  # nodes over real DDS: run alone (setup.cfg)

HERE = Path(__file__).parent


def test_profile_is_installed_and_gives_shared_memory_a_large_segment():
    path = large_frames_profile()
    assert path.is_file() and "share/inseggan_ros/config" in str(path), path
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    root = ET.parse(path).getroot()
    shm = [t for t in root.iterfind(".//f:transport_descriptor", ns)
           if t.findtext("f:type", namespaces=ns) == "SHM"]
    assert len(shm) == 1 and int(shm[0].findtext("f:segment_size", namespaces=ns)) >= 8 * 2**20


def test_use_profile_keeps_a_profile_the_user_chose():
    env = {}
    assert use_large_frames_profile(env) == str(large_frames_profile())
    assert all(env[v] == str(large_frames_profile()) for v in PROFILE_VARIABLES)
    mine = {PROFILE_VARIABLES[0]: "/etc/my_profile.xml"}
    assert use_large_frames_profile(mine) == "/etc/my_profile.xml"
    assert mine == {PROFILE_VARIABLES[0]: "/etc/my_profile.xml"}


def test_large_frames_arrive_between_processes_with_the_profile():
    """30 frames of 1280 x 720 16UC1 (1.8 MB) at 15 Hz, best effort, from one process to
    another: with the profile, (nearly) all of them arrive."""
    env = dict(os.environ)
    use_large_frames_profile(env)
    sub = subprocess.Popen([sys.executable, str(HERE / "large_frames.py"), "sub", "30", "25"],
                           stdout=subprocess.PIPE, text=True, env=env)
    assert sub.stdout.readline().strip() == "ready"
    pub = subprocess.run([sys.executable, str(HERE / "large_frames.py"), "pub", "30", "15"],
                         env=env, timeout=60, capture_output=True, text=True)
    assert pub.returncode == 0, pub.stderr
    out, _ = sub.communicate(timeout=40)
    assert int(out.strip().splitlines()[-1]) >= 28, out
