"""bin_replay and the segmenter side by side, connected by their default topics (no remap).

    ros2 launch inseggan_ros demo.launch.py                        # live simulated cylinders
    ros2 launch inseggan_ros demo.launch.py source:=bag bag_path:=cylinder_sim
    ros2 launch inseggan_ros demo.launch.py object:=hex_nut model:=hex_nut

Arguments: source (sim or bag), object, bag_path, rate (frames per second), model, params_file,
namespace. The segmenter's labels, picks and markers are under <namespace>/segmenter/.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description():
    share = FindPackageShare("inseggan_ros")
    arg = LaunchConfiguration
    replay = Node(package="inseggan_ros", executable="bin_replay", name="bin_replay",
                  namespace=arg("namespace"), output="screen", emulate_tty=True,
                  parameters=[{"source": arg("source"), "object": arg("object"),
                               "bag_path": arg("bag_path"), "loop": True,
                               "rate": arg("rate")}])
    segmenter = IncludeLaunchDescription(
        PythonLaunchDescriptionSource(PathJoinSubstitution([share, "launch",
                                                            "segmenter.launch.py"])),
        launch_arguments={"model": arg("model"), "params_file": arg("params_file"),
                          "namespace": arg("namespace")}.items())
    return LaunchDescription([
        DeclareLaunchArgument("source", default_value="sim", description="sim or bag"),
        DeclareLaunchArgument("object", default_value="cylinder",
                              description="object to simulate (source sim)"),
        DeclareLaunchArgument("bag_path", default_value="cylinder_sim",
                              description="bag path or shipped bag name (source bag)"),
        DeclareLaunchArgument("rate", default_value="5.0", description="frames per second"),
        DeclareLaunchArgument("model", default_value="",
                              description="checkpoint or shipped model name ('' = cylinder)"),
        DeclareLaunchArgument("params_file",
                              default_value=PathJoinSubstitution([share, "config",
                                                                  "realtime.yaml"]),
                              description="ROS 2 parameters file for the segmenter"),
        DeclareLaunchArgument("namespace", default_value="", description="both nodes' namespace"),
        replay,
        segmenter,
    ])
