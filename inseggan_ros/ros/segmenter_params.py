"""The segmenter's parameters: their declarations (names, defaults, descriptions, ranges) and the
checks of the values that rclpy's ranges cannot express. `segmenter.py` uses them."""
from __future__ import annotations

import math

from rcl_interfaces.msg import ParameterType

from inseggan_ros.core import settings
from inseggan_ros.core.paths import DEFAULT_MODEL
from inseggan_ros.ros import common
from inseggan_ros.ros.common import ConfigError

d = common.descriptor

# changeable at run time, the same for every model: where the picks are published
TARGET_NAMES = ("target_frame", "target_translation", "target_rotation")
# changeable at run time, their defaults the model's (declared once a model is loaded)
OUTPUT_NAMES = ("publish_masks", "publish_overlay", "publish_reconstruction",
                "resolution_change_frames")


def parse_roi(v) -> tuple[int, int, int, int] | None:
    v = list(v)
    if not v:
        return None
    if len(v) != 4 or not (0 <= v[0] < v[2] and 0 <= v[1] < v[3]):
        raise ConfigError(f"roi {v} invalid; valid: [] (find the bin) or [x0, y0, x1, y1] "
                          "pixels with 0 <= x0 < x1, 0 <= y0 < y1")
    return tuple(int(x) for x in v)


def parse_polygon(v) -> tuple | None:
    v = list(v)
    if not v:
        return None
    if len(v) < 6 or len(v) % 2 or not all(math.isfinite(x) for x in v):
        raise ConfigError(f"bin_polygon {v} invalid; valid: [] or [u0, v0, u1, v1, u2, v2, ...] "
                          "(at least 3 finite pixel points)")
    return tuple(zip(v[0::2], v[1::2]))


def startup() -> dict:
    """The read-only parameters, set at start."""
    return {
        "model_path": ("", d("checkpoint file, or the name of a model shipped in "
                             f"share/inseggan_ros/models ('' = {DEFAULT_MODEL})", read_only=True)),
        "device": ("auto", d("auto (cuda when available), cpu or cuda", read_only=True)),
        "threads": (1, d("CPU threads for inference (1 leaves the other cores to DDS and the "
                         "rest of the robot)", read_only=True, int_range=(1, 256))),
        "superpixel_thread": (True, d(
            "make what depends on the frame alone, the centre votes (centre_votes) and the "
            "depth superpixels (superpixel_scale, split_scale), in a second thread while the "
            "encoder runs: the same labels, sooner where a second core is free",
            read_only=True)),
        "input_transport": ("raw", d(
            "raw: sensor_msgs/Image on the depth topic; compressedDepth: image_transport's "
            "sensor_msgs/CompressedImage on <depth topic>/compressedDepth", read_only=True)),
        "autostart": (True, d(
            "configure (load the model) and activate (subscribe) at start, as a plain node; "
            "false: wait in the lifecycle state unconfigured for ~/change_state",
            read_only=True)),
        "diagnostics_period": (1.0, d("seconds between /diagnostics messages", read_only=True,
                                      float_range=(0.05, 60.0))),
        "latency_window": (1000, d("frames over which /diagnostics reports latency percentiles",
                                   read_only=True, int_range=(10, 1_000_000))),
        "bin_check_window": (15, d(
            "frames whose label-free measures' medians /diagnostics compares with the model "
            "card's", read_only=True, int_range=(1, 10_000))),
        "segment_next_timeout": (5.0, d(
            "seconds ~/segment_next waits for a frame before it answers with failure",
            read_only=True, float_range=(0.1, 600.0))),
        "publish_picks": (True, d("publish ~/picks, ~/pick_confidence and ~/markers (computed "
                                  "only when subscribed; needs CameraInfo)", read_only=True)),
        "pick_free_rise": (0.003, d(
            "metres: a neighbouring instance higher than this where the two meet lies on an "
            "instance, which then is not free (picks: free ones first)", read_only=True,
            float_range=(0.0, 0.1))),
        "pick_normal_radius": (0.004, d(
            "metres: the patch around a pick's centroid that its normal is fitted to",
            read_only=True, float_range=(0.0005, 0.1))),
        "use_tf": (False, d(
            "look the transform target_frame <- the depth frame up in tf (needs tf2_ros) "
            "instead of target_translation and target_rotation", read_only=True)),
    }


def target() -> dict:
    """Where the picks and markers are published (changeable at run time)."""
    return {
        "target_frame": ("", d(
            "frame the picks and markers are published in ('' = the depth image's own "
            "frame, no transform)")),
        "target_translation": ([0.0, 0.0, 0.0], d(
            "[x, y, z] metres: the camera frame's origin in target_frame (the transform "
            "target_frame <- camera, as tf2_echo target_frame camera_frame prints it)",
            type_=ParameterType.PARAMETER_DOUBLE_ARRAY)),
        "target_rotation": ([0.0, 0.0, 0.0, 1.0], d(
            "[x, y, z, w] unit quaternion: the camera frame's orientation in target_frame "
            "(a norm further than 0.001 from 1 is refused, a nearer one normalised)",
            type_=ParameterType.PARAMETER_DOUBLE_ARRAY)),
    }


def check_target(values: dict):
    """{target_frame, target_translation, target_rotation} -> (frame, translation (3,),
    unit quaternion (4,)); raises ConfigError naming what is wrong."""
    from inseggan_ros.runtime.picks import check_transform

    try:
        t, q = check_transform(values["target_translation"], values["target_rotation"])
    except ValueError as e:
        raise ConfigError(str(e)) from None
    frame = str(values["target_frame"])
    if not frame and (t.any() or abs(q[3]) != 1.0):
        raise ConfigError("target_translation and target_rotation need target_frame, the "
                          "frame they lead to (target_frame '' publishes in the camera's frame)")
    return frame, t, q


def runtime(model) -> tuple[list[str], dict]:
    """(names, specs) of the parameters changeable at run time whose defaults are `model`'s
    (a segment.Segmenter): the bin, the preprocessing, the inference settings, the outputs."""
    prep, cfg = model.prep_cfg, model.inference
    specs = {
        "roi": ([], d("bin region [x0, y0, x1, y1] in pixels (end exclusive); [] = find the bin "
                      "floor automatically (once per resolution)",
                      type_=ParameterType.PARAMETER_INTEGER_ARRAY)),
        "bin_polygon": ([], d("bin outline [u0, v0, u1, v1, ...] in pixels; pixels outside are "
                              "background; [] = none",
                              type_=ParameterType.PARAMETER_DOUBLE_ARRAY)),
        "floor_depth": (0.0, d("metres from the camera to a level bin floor; 0 = fit the floor "
                               "as a plane per frame", float_range=(0.0, 20.0))),
        "floor_plane": ([], d(
            "the bin floor as a plane for a fixed, tilted camera: [a, b, c] with 1/depth = "
            "a u + b v + c at pixel (u, v) (column, row) of the full frame, as "
            "preprocess.fit_floor_plane measures it; [] = fit it per frame; not together with "
            "floor_depth", type_=ParameterType.PARAMETER_DOUBLE_ARRAY)),
        "min_height": (float(prep.min_height), d(
            "metres above the floor below which a pixel is background (about half an object "
            "height)", float_range=(0.0, float(prep.max_height)))),
        "rim_band": (float(prep.rim_band), d(
            "how far beyond the bin region labels are carried onto objects leaning over its "
            "edge, as a fraction of the region's longer side (0 = labels stay inside)",
            float_range=(0.0, 1.0))),
        "rim_step": (float(prep.rim_step), d(
            "metres: the largest depth step between neighbouring pixels of one surface when "
            "carrying labels beyond the bin region", float_range=(0.0001, 0.1))),
        "tau": (float(model.tau), d("render threshold in [-1, 1] (default: calibrated, stored "
                                    "in the model)", float_range=(-1.0, 1.0))),
    }
    model_values = settings.values(cfg)  # the inference settings: one name each everywhere
    specs.update({x.name: (model_values[x.name], d(
        x.doc + (f"; one of {', '.join(x.choices)}" if x.choices else "")
        + " (default: the model's)", int_range=x.range if x.type is int else None))
        for x in settings.exposed()})
    specs.update({
        "publish_masks": (True, d("publish ~/masks")),
        "publish_overlay": (True, d("publish ~/overlay (computed only when subscribed)")),
        "publish_reconstruction": (True, d("publish ~/reconstruction (only when subscribed)")),
        "resolution_change_frames": (10, d(
            "frames of one new resolution in a row after which the node adopts it (the earlier "
            "ones are skipped)", int_range=(1, 10_000))),
    })
    return list(specs), specs
