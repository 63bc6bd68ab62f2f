"""The segmenter alone.

    ros2 launch inseggan_ros segmenter.launch.py
    ros2 launch inseggan_ros segmenter.launch.py model:=hex_nut namespace:=cell1 \
        depth_topic:=/camera/camera/depth/image_rect_raw

Launch arguments, name: meaning
    model              checkpoint file or shipped model name ('' = the default, cylinder)
    params_file        ROS 2 parameters file (default: config/realtime.yaml, the models' own
                       settings); a `model` given here wins over the file's model_path
    namespace          the node's namespace (its relative topics move with it)
    depth_topic        the depth image (default: camera/depth/image_rect_raw, relative)
    camera_info_topic  its CameraInfo ('' = the camera_info beside depth_topic)
    autostart          true (default): the node configures and activates itself; false: it
                       waits, unconfigured, for a lifecycle manager's ~/change_state
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

DEPTH = "camera/depth/image_rect_raw"
CAMERA_INFO = "camera/depth/camera_info"


def _segmenter(context, *args, **kwargs):
    value = lambda name: LaunchConfiguration(name).perform(context)  # noqa: E731
    remappings = [(DEPTH, value("depth_topic"))]
    if value("camera_info_topic"):  # else the node takes the camera_info beside the depth topic
        remappings.append((CAMERA_INFO, value("camera_info_topic")))
    parameters = [value("params_file")]
    if value("model"):
        parameters.append({"model_path": value("model")})
    autostart = value("autostart").lower()
    if autostart not in ("true", "false"):
        raise ValueError(f"autostart:={autostart} invalid; valid: true, false")
    parameters.append({"autostart": autostart == "true"})
    return [Node(package="inseggan_ros", executable="segmenter", name="segmenter",
                 namespace=value("namespace"), parameters=parameters, remappings=remappings,
                 output="screen", emulate_tty=True)]


def generate_launch_description():
    share = FindPackageShare("inseggan_ros")
    return LaunchDescription([
        DeclareLaunchArgument("model", default_value="",
                              description="checkpoint or shipped model name ('' = cylinder)"),
        DeclareLaunchArgument("params_file",
                              default_value=PathJoinSubstitution([share, "config",
                                                                  "realtime.yaml"]),
                              description="ROS 2 parameters file for the segmenter"),
        DeclareLaunchArgument("namespace", default_value="", description="the node's namespace"),
        DeclareLaunchArgument("depth_topic", default_value=DEPTH,
                              description="depth image topic"),
        DeclareLaunchArgument("camera_info_topic", default_value="",
                              description="CameraInfo topic ('' = beside depth_topic)"),
        DeclareLaunchArgument("autostart", default_value="true",
                              description="true: configure and activate at start; false: wait "
                                          "for ~/change_state (a lifecycle manager)"),
        OpaqueFunction(function=_segmenter),
    ])
