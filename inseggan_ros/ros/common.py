"""What the package's nodes share: the start-up error type, parameter declaration, the Fast DDS
profile for large frames, and the `main` that runs a node until Ctrl-C.

Default topic names are those of the usual camera drivers (relative, so that a namespace or a
remap moves them): bin_replay publishes them and the segmenter listens on them, so the two
connect with no remap.
"""
from __future__ import annotations

import os
import sys

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.executors import ExternalShutdownException

from inseggan_ros.core.paths import NotFoundError

DEPTH_TOPIC = "camera/depth/image_rect_raw"
CAMERA_INFO_TOPIC = "camera/depth/camera_info"
LABELS_TOPIC = "camera/depth/instance_labels"  # bin_replay's ground truth, when known


class ConfigError(Exception):
    """A parameter value the node cannot start with."""


class FrameError(ValueError):
    """A frame (or its picks) the node skips; `reason` is the diagnostics counter it goes to."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


def descriptor(desc: str, read_only: bool = False, float_range=None, int_range=None,
               type_=None) -> ParameterDescriptor:
    """A ParameterDescriptor; the ranges are (from, to), enforced by rclpy on every set."""
    pd = ParameterDescriptor(description=desc, read_only=read_only)
    if type_ is not None:
        pd.type = type_
    if float_range:
        pd.floating_point_range = [FloatingPointRange(
            from_value=float(float_range[0]), to_value=float(float_range[1]), step=0.0)]
    if int_range:
        pd.integer_range = [IntegerRange(from_value=int(int_range[0]), to_value=int(int_range[1]),
                                         step=1)]
    return pd


def declare(node, specs: dict) -> None:
    """Declare {name: (default, descriptor)}; an empty-list default takes the descriptor's type
    (an empty list has none of its own). A bad value given on the command line -> ConfigError."""
    from rclpy.parameter import Parameter

    for name, (default, desc) in specs.items():
        if isinstance(default, list) and not default:
            default = Parameter.Type(desc.type)
        try:
            node.declare_parameter(name, default, desc)
        except Exception as e:  # out of range or wrong type on the command line
            raise ConfigError(f"parameter {name}: {e}") from None


def use_large_frames_profile() -> str | None:
    """Point Fast DDS at the shipped large-frames profile (config/fastdds_large_frames.xml) when
    the user has set no profile and the middleware is Fast DDS; call before rclpy.init.
    -> a line for the log when it did so, else None.

    Why: with Fast DDS's built-in transports most large depth frames sent best-effort at camera
    rates never arrive (inseggan_ros/dds.py has the figures); a plain `ros2 run` should not
    depend on an environment variable the user has to know about."""
    from inseggan_ros.ros.dds import PROFILE_VARIABLES, use_large_frames_profile as apply_profile

    if any(os.environ.get(v) for v in PROFILE_VARIABLES):
        return None
    rmw = os.environ.get("RMW_IMPLEMENTATION", "")
    if rmw and not rmw.startswith("rmw_fastrtps"):
        return None
    path = apply_profile(os.environ)
    return (f"Fast DDS profile for large frames: {path} (set FASTRTPS_DEFAULT_PROFILES_FILE "
            "to use another)")


def run(name: str, make_node, args=None, errors: tuple = (), spin=None) -> int:
    """`main` of a node: set up DDS, build the node with `make_node()`, spin it (`spin(node)`,
    default rclpy.spin) until Ctrl-C or shutdown. A ConfigError, a NotFoundError or one of
    `errors` at start-up -> one line '<name>: error: ...' on stderr and exit status 1.
    The node's `close()`, when it has one, runs before it is destroyed."""
    note = use_large_frames_profile()
    rclpy.init(args=args)
    node = None
    try:
        if note:
            rclpy.logging.get_logger(name).info(note)
        node = make_node()
        (spin or rclpy.spin)(node)
        return 0
    except (ConfigError, NotFoundError, *errors) as e:
        print(f"{name}: error: {e}", file=sys.stderr)
        return 1
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    except Exception:
        if not rclpy.ok():  # Ctrl-C during start-up: rclpy shut the context down under the
            return 0  # node being built, which then fails; that is a normal stop
        raise
    finally:
        if node is not None:
            if hasattr(node, "close"):
                node.close()
            node.destroy_node()
        rclpy.try_shutdown()
