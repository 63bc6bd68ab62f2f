"""The segmenter on an Intel RealSense D435 (848 x 480 depth), with config/d435.yaml.

    ros2 launch realsense2_camera rs_launch.py depth_module.depth_profile:=848x480x30 \
        enable_color:=false                       # the camera, in its own terminal; then
    ros2 launch inseggan_ros d435.launch.py
    ros2 launch inseggan_ros d435.launch.py start_camera:=true     # both at once

realsense2_camera 4.x publishes /camera/camera/depth/image_rect_raw and
/camera/camera/depth/camera_info (camera_namespace and camera_name both 'camera'); the segmenter
is remapped to them. Arguments: model, namespace, depth_topic, camera_info_topic (as
segmenter.launch.py), start_camera (also start realsense2_camera's rs_launch.py at 848 x 480,
depth only; needs the realsense2_camera package).
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, IncludeLaunchDescription
from launch.conditions import IfCondition
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.substitutions import FindPackageShare


def generate_launch_description():
    share = FindPackageShare("inseggan_ros")
    arg = LaunchConfiguration
    camera = IncludeLaunchDescription(
        PythonLaunchDescriptionSource(PathJoinSubstitution([
            FindPackageShare("realsense2_camera"), "launch", "rs_launch.py"])),
        # the profile's name changed within 4.x (depth_module.profile before 4.54)
        launch_arguments={"depth_module.depth_profile": "848x480x30",
                          "depth_module.profile": "848x480x30",
                          "enable_color": "false", "enable_depth": "true"}.items(),
        condition=IfCondition(arg("start_camera")))
    segmenter = IncludeLaunchDescription(
        PythonLaunchDescriptionSource(PathJoinSubstitution([share, "launch",
                                                            "segmenter.launch.py"])),
        launch_arguments={"model": arg("model"),
                          "params_file": PathJoinSubstitution([share, "config", "d435.yaml"]),
                          "namespace": arg("namespace"), "depth_topic": arg("depth_topic"),
                          "camera_info_topic": arg("camera_info_topic")}.items())
    return LaunchDescription([
        DeclareLaunchArgument("model", default_value="",
                              description="checkpoint or shipped model name ('' = cylinder)"),
        DeclareLaunchArgument("namespace", default_value="", description="the node's namespace"),
        DeclareLaunchArgument("depth_topic", default_value="/camera/camera/depth/image_rect_raw",
                              description="the D435's depth image"),
        DeclareLaunchArgument("camera_info_topic",
                              default_value="/camera/camera/depth/camera_info",
                              description="the D435's depth CameraInfo"),
        DeclareLaunchArgument("start_camera", default_value="false",
                              description="also start realsense2_camera (rs_launch.py)"),
        camera,
        segmenter,
    ])
