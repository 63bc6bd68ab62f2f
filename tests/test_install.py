"""The package as `colcon build` installs it and as `ros2 run` resolves its executables."""
import os
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

from conftest import REPO, installed_executable

ROS2RUN = REPO / "scripts" / "ros2run"


def test_package_xml_declares_real_dependencies():
    root = ET.parse(REPO / "package.xml").getroot()
    assert root.get("format") == "3" and root.findtext("name") == "inseggan_ros"
    deps = {e.text for e in root if e.tag.endswith("depend")}
    for dep in ("rclpy", "sensor_msgs", "std_msgs", "diagnostic_msgs", "python3-numpy",
                "python3-opencv", "python3-pytest"):
        assert dep in deps
    assert root.find("export/build_type").text == "ament_python"


def test_executables_resolve_like_ros2_run():
    from ament_index_python.packages import get_package_prefix, get_package_share_directory

    prefix = Path(get_package_prefix("inseggan_ros"))
    assert str(prefix) in os.environ["AMENT_PREFIX_PATH"].split(os.pathsep)
    for exe in ("bin_replay", "inseggan"):
        path = installed_executable(exe)
        assert path == prefix / "lib" / "inseggan_ros" / exe
        assert path.is_file() and os.access(path, os.X_OK)
    share = Path(get_package_share_directory("inseggan_ros"))
    assert (share / "package.xml").is_file()
    assert (share / "bags" / "cylinder_sim" / "metadata.yaml").is_file()


def test_ros2run_script_runs_the_installed_executable():
    p = subprocess.run([str(ROS2RUN), "inseggan_ros", "inseggan", "--help"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0 and "simulate" in p.stdout
    p = subprocess.run([str(ROS2RUN), "inseggan_ros", "nope"], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 1 and "executables: bin_replay inseggan" in p.stderr
    env = dict(os.environ, AMENT_PREFIX_PATH="/nonexistent")
    p = subprocess.run([str(ROS2RUN), "inseggan_ros", "inseggan"], capture_output=True,
                       text=True, timeout=60, env=env)
    assert p.returncode == 1 and "not found on AMENT_PREFIX_PATH" in p.stderr
