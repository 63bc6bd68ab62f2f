r"""segmenter: depth frames in, instance labels and masks out (InSeGAN, a trained model).

    ros2 run inseggan_ros segmenter                                  # the shipped default model
    ros2 run inseggan_ros segmenter --ros-args \
        -r camera/depth/image_rect_raw:=/camera/camera/depth/image_rect_raw \
        -p model_path:=models/cylinder/model.pt -p roi:=[58,58,166,166]

Subscribes (sensor-data QoS, keep-last 1: a slow frame never builds a queue; relative names, the
ones bin_replay and camera drivers publish, so the two connect with no remap):
    camera/depth/image_rect_raw  sensor_msgs/Image   16UC1 / mono16 millimetres or 32FC1 metres
    camera/depth/camera_info     sensor_msgs/CameraInfo, for the picks (the latest is used);
                                 when only the depth topic is remapped, the camera_info beside
                                 it (the same folder), as image_transport pairs them
Publishes, with the input's header (stamp and frame_id unchanged):
    ~/labels              sensor_msgs/Image mono8: 0 background, 1..n instances, input size
    ~/masks               sensor_msgs/Image 8UC<n>: channel k is 255 where instance k+1 is
    ~/overlay             sensor_msgs/Image rgb8 colour overlay (only computed when subscribed)
    ~/reconstruction      sensor_msgs/Image 32FC1 metres, the model's re-rendered depth
                          (only when subscribed; 0 outside the bin)
    ~/picks               geometry_msgs/PoseArray, one pose per instance in pick order
                          (picks.py: free ones first, then the top-most): position = its
                          visible surface's centroid, orientation's z axis = the surface
                          normal there, toward the camera; camera optical frame (only when
                          ~/picks or ~/markers is subscribed)
    ~/markers             visualization_msgs/MarkerArray for RViz: normal arrows and ranks
    /diagnostics          diagnostic_msgs/DiagnosticArray: rate, latency, error counters; a
                          second status '<node>: picks' (WARN while CameraInfo is missing or
                          of another size: labels are still published, picks not)
A bad frame (encoding, size, empty, no valid depth, a resolution change) is logged (throttled),
counted in diagnostics and skipped; the node keeps serving. A missing or incompatible model
stops the node at start-up with one clear error line. Unless FASTRTPS_DEFAULT_PROFILES_FILE
is set, the node uses the shipped Fast DDS profile for large frames (common.py).
"""
from __future__ import annotations

import copy
import math
import sys
import time
from collections import Counter, deque
from dataclasses import replace

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterType, SetParametersResult
from rclpy.node import Node
from rclpy.qos import QoSHistoryPolicy, qos_profile_sensor_data
from sensor_msgs.msg import Image

from inseggan_ros.core import image_codec
from inseggan_ros.core import settings
from inseggan_ros.core.checkpoint import CheckpointError
from inseggan_ros.ros import common
from inseggan_ros.ros import conversions

# DEFAULT_MODEL and resolve_model are imported from here by the tests and bench_node
from inseggan_ros.core.paths import DEFAULT_MODEL, resolve_model  # noqa: F401
from inseggan_ros.ros.common import ConfigError


def _parse_roi(v) -> tuple[int, int, int, int] | None:
    v = list(v)
    if not v:
        return None
    if len(v) != 4 or not (0 <= v[0] < v[2] and 0 <= v[1] < v[3]):
        raise ConfigError(f"roi {v} invalid; valid: [] (find the bin) or [x0, y0, x1, y1] "
                          "pixels with 0 <= x0 < x1, 0 <= y0 < y1")
    return tuple(int(x) for x in v)


def _parse_polygon(v) -> tuple | None:
    v = list(v)
    if not v:
        return None
    if len(v) < 6 or len(v) % 2 or not all(math.isfinite(x) for x in v):
        raise ConfigError(f"bin_polygon {v} invalid; valid: [] or [u0, v0, u1, v1, u2, v2, ...] "
                          "(at least 3 finite pixel points)")
    return tuple(zip(v[0::2], v[1::2]))


class FrameError(ValueError):
    """A frame the node skips; `reason` is the diagnostics counter it goes to."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


class SegmenterNode(Node):
    def __init__(self, **kwargs):
        super().__init__("segmenter", **kwargs)
        self._declare_startup()
        self.model_path = resolve_model(self.get_parameter("model_path").value)
        device = self.get_parameter("device").value
        if device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"parameter device={device!r} invalid; valid: auto, cpu, cuda")
        import torch

        torch.set_num_threads(self.get_parameter("threads").value)
        from inseggan_ros.runtime.segment import Segmenter as Model

        try:
            self.model = Model.from_checkpoint(
                self.model_path, device=device,
                superpixel_thread=self.get_parameter("superpixel_thread").value)
        except ValueError as e:  # e.g. cuda asked for but not available
            raise ConfigError(f"parameter device={device!r}: {e}") from None
        # a training checkpoint stores no settings: it runs with realtime.yaml's, as every
        # exported model starts with, and a parameters file applies over those
        self.model.inference = settings.file_base(self.model.inference,
                                                  self.model.stored_settings)
        self._declare_runtime()
        self.p = {}
        try:
            self._apply({name: self._value(name) for name in self._runtime_names})
        except ValueError as e:
            raise ConfigError(str(e)) from None
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._warm_up()

        n = self.model.model_cfg.n_instances
        self.pub_labels = self.create_publisher(Image, "~/labels", 5)
        self.pub_masks = self.create_publisher(Image, "~/masks", 5)
        self.pub_overlay = self.create_publisher(Image, "~/overlay", 5)
        self.pub_recon = self.create_publisher(Image, "~/reconstruction", 5)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        qos = copy.copy(qos_profile_sensor_data)  # rclpy's profile is shared: change a copy
        qos.history, qos.depth = QoSHistoryPolicy.KEEP_LAST, 1
        self.sub = self.create_subscription(Image, common.DEPTH_TOPIC, self._on_depth, qos)
        if self.resolve_topic_name("depth") != self.resolve_topic_name("depth", only_expand=True):
            self.get_logger().warning(  # the name this node subscribed to before
                f"the remap of 'depth' has no effect: the depth topic is {common.DEPTH_TOPIC} "
                f"(remap that name: -r {common.DEPTH_TOPIC}:=/your/depth/topic)")
        self._init_picks(qos)

        self.counts = Counter()  # received, segmented, skipped and skipped:<reason>
        window = self.get_parameter("latency_window").value
        self.latency_ms = deque(maxlen=window)  # received -> labels published
        self.inference_ms = deque(maxlen=window)  # segment.Segmenter call alone
        self.conversion_ms = deque(maxlen=window)  # message decode + encode
        self.stamps = deque(maxlen=1000)  # monotonic time of each segmented frame
        self.last_error = ""
        self._logged = {}  # (reason, message start) -> when last logged
        self._shape = None  # resolution of the last good frame
        self._new_shape = (None, 0)  # (shape, consecutive frames) of a changed resolution
        self._roi_cache = {}  # frame shape -> the bin regions found in its first frames
        self.create_timer(self.get_parameter("diagnostics_period").value, self._publish_diagnostics)
        self.get_logger().info(
            f"model {self.model_path} ({n} x instances, tau {self.model.tau:.3f}, device "
            f"{self.model.device}); listening on {self.sub.topic_name} (camera info: "
            f"{self.sub_info.topic_name})")

    # ------------------------------------------------------------------ picks
    def _init_picks(self, qos) -> None:
        """The CameraInfo subscription (the latest message is kept), the pick publishers."""
        from geometry_msgs.msg import PoseArray
        from sensor_msgs.msg import CameraInfo
        from visualization_msgs.msg import MarkerArray

        from inseggan_ros.runtime.picks import PickConfig

        self.pick_cfg = PickConfig(normal_radius=self.get_parameter("pick_normal_radius").value,
                                   free_rise=self.get_parameter("pick_free_rise").value)
        self.camera_info = None  # the latest CameraInfo message
        self.sub_info = self.create_subscription(
            CameraInfo, self._camera_info_topic(),
            lambda m: setattr(self, "camera_info", m), qos)
        self.pub_picks = self.create_publisher(PoseArray, "~/picks", 5)
        self.pub_markers = self.create_publisher(MarkerArray, "~/markers", 5)
        self.pick_counts = Counter()  # published, skipped:<reason>
        self.pick_problem = ""  # why the last frame got no picks ('' = it got them)
        self.last_picks = ""  # the last published pick order, for /diagnostics

    def _camera_info_topic(self) -> str:
        """camera_info beside the depth topic (as image_transport pairs them): when only the
        depth topic is remapped, the camera_info of the same folder; a remap of
        camera/depth/camera_info itself wins."""
        info = self.resolve_topic_name(common.CAMERA_INFO_TOPIC)
        if info != self.resolve_topic_name(common.CAMERA_INFO_TOPIC, only_expand=True):
            return info  # remapped explicitly
        return self.sub.topic_name.rsplit("/", 1)[0] + "/camera_info"

    def _camera_matrix(self, shape: tuple[int, int]):
        """K of the latest CameraInfo for a depth frame of `shape`; raises FrameError(reason,
        why) when there is none, its size differs or its K is unusable."""
        from inseggan_ros.runtime.picks import check_intrinsics

        if self.camera_info is None:
            raise FrameError("no_camera_info", f"no CameraInfo received on "
                                               f"{self.sub_info.topic_name}: no picks")
        w, h, K = conversions.camera_info_size_and_K(self.camera_info)
        if (h, w) != tuple(shape):
            raise FrameError("camera_info_size", f"CameraInfo on {self.sub_info.topic_name} is "
                             f"{w}x{h} but the depth is {shape[1]}x{shape[0]}: no picks")
        try:
            return check_intrinsics(K)
        except ValueError as e:
            raise FrameError("camera_info_k", f"CameraInfo on {self.sub_info.topic_name}: {e}: "
                             "no picks") from None

    def _publish_picks(self, msg: Image, depth: np.ndarray, seg) -> None:
        """Picks of a segmented frame on ~/picks and ~/markers, with the input's header. Any
        problem (no or mismatched CameraInfo) is counted, shown in /diagnostics and logged
        (throttled); the labels were published already."""
        from inseggan_ros.runtime.picks import compute_picks, hidden_from_renders

        if not self.get_parameter("publish_picks").value:
            return
        try:
            K = self._camera_matrix(depth.shape)
        except FrameError as e:
            self.pick_counts[f"skipped:{e.reason}"] += 1
            self.pick_problem = str(e)
            self._warn_throttled(e.reason, str(e))
            return
        self.pick_problem = ""
        if self.pub_picks.get_subscription_count() + self.pub_markers.get_subscription_count() == 0:
            return
        occluded = hidden_from_renders(seg.renders64, seg.labels64, self.p["tau"], seg.scores)
        picks = compute_picks(depth, seg.labels, K, occluded, self.pick_cfg)
        self.pub_picks.publish(conversions.picks_to_pose_array(picks, msg.header))
        if self.pub_markers.get_subscription_count() > 0:
            self.pub_markers.publish(conversions.picks_to_markers(picks, msg.header))
        self.pick_counts["published"] += 1
        self.last_picks = " ".join(
            f"#{p.instance}{'' if p.free else '(under)'}@{p.position[2]:.3f}m" for p in picks)
        self.get_logger().debug(f"picks: {self.last_picks or 'none'}")

    def _warn_throttled(self, reason: str, message: str, period: float = 5.0) -> None:
        key, now = ("warn", reason), time.monotonic()
        if now - self._logged.get(key, -math.inf) >= period:
            self._logged[key] = now
            self.get_logger().warning(message)

    def _warm_up(self) -> None:
        """One inference on a synthetic input before subscribing, so that the first real frame
        does not pay PyTorch's one-time set-up (the demo's first frame took 1.7 s without)."""
        s = self.model.prep_cfg.size
        x = np.full((1, 1, s, s), -1.0, np.float32)
        x[0, 0, s // 4:s // 2, s // 4:3 * s // 4] = 0.0  # one flat object
        self.model.segment_batch(x, settings=self._settings())

    def _settings(self):
        """The model's test-time settings (`InferenceConfig`) as the parameters now set them."""
        return settings.apply(self.model.inference, self.p)

    # ------------------------------------------------------------------ parameters
    _descriptor = staticmethod(common.descriptor)

    def _declare(self, specs: dict) -> None:
        common.declare(self, specs)

    def _declare_startup(self) -> None:
        d = self._descriptor
        self._declare({
            "model_path": ("", d("checkpoint file, or the name of a model shipped in "
                                 f"share/inseggan_ros/models ('' = {DEFAULT_MODEL})",
                                 read_only=True)),
            "device": ("auto", d("auto (cuda when available), cpu or cuda", read_only=True)),
            "threads": (1, d("CPU threads for inference (1 leaves the other cores to DDS and "
                             "the rest of the robot)", read_only=True, int_range=(1, 256))),
            "superpixel_thread": (True, d(
                "make what depends on the frame alone, the centre votes (centre_votes) and the "
                "depth superpixels (superpixel_scale, split_scale), in a second thread while "
                "the encoder runs: the same labels, sooner where a second core is free",
                read_only=True)),
            "diagnostics_period": (1.0, d("seconds between /diagnostics messages", read_only=True,
                                          float_range=(0.05, 60.0))),
            "latency_window": (1000, d("frames over which /diagnostics reports latency "
                                       "percentiles", read_only=True, int_range=(10, 1_000_000))),
            "publish_picks": (True, d("publish ~/picks and ~/markers (computed only when "
                                      "subscribed; needs CameraInfo)", read_only=True)),
            "pick_free_rise": (0.003, d(
                "metres: a neighbouring instance higher than this where the two meet lies on an "
                "instance, which then is not free (picks: free ones first)", read_only=True,
                float_range=(0.0, 0.1))),
            "pick_normal_radius": (0.004, d(
                "metres: the patch around a pick's centroid that its normal is fitted to",
                read_only=True, float_range=(0.0005, 0.1))),
        })

    def _declare_runtime(self) -> None:
        d, prep, cfg = self._descriptor, self.model.prep_cfg, self.model.inference
        self._runtime_names = ["roi", "bin_polygon", "floor_depth", "floor_plane", "min_height",
                               "rim_band",
                               "rim_step", "tau",
                               *(x.name for x in settings.exposed()),
                               "publish_masks", "publish_overlay", "publish_reconstruction",
                               "resolution_change_frames"]
        self._declare({
            "roi": ([], d("bin region [x0, y0, x1, y1] in pixels (end exclusive); [] = find the "
                          "bin floor automatically (once per resolution)",
                          type_=ParameterType.PARAMETER_INTEGER_ARRAY)),
            "bin_polygon": ([], d("bin outline [u0, v0, u1, v1, ...] in pixels; pixels outside "
                                  "are background; [] = none",
                                  type_=ParameterType.PARAMETER_DOUBLE_ARRAY)),
            "floor_depth": (0.0, d("metres from the camera to a level bin floor; 0 = fit the "
                                   "floor as a plane per frame", float_range=(0.0, 20.0))),
            "floor_plane": ([], d(
                "the bin floor as a plane for a fixed, tilted camera: [a, b, c] with 1/depth = "
                "a u + b v + c at pixel (u, v) (column, row) of the full frame, as "
                "preprocess.fit_floor_plane measures it; [] = fit it per frame; not together "
                "with floor_depth", type_=ParameterType.PARAMETER_DOUBLE_ARRAY)),
            "min_height": (float(prep.min_height),
                           d("metres above the floor below which a pixel is background (about "
                             "half an object height)",
                             float_range=(0.0, float(prep.max_height)))),
            "rim_band": (float(prep.rim_band), d(
                "how far beyond the bin region labels are carried onto objects leaning over its "
                "edge, as a fraction of the region's longer side (0 = labels stay inside)",
                float_range=(0.0, 1.0))),
            "rim_step": (float(prep.rim_step), d(
                "metres: the largest depth step between neighbouring pixels of one surface when "
                "carrying labels beyond the bin region", float_range=(0.0001, 0.1))),
            "tau": (float(self.model.tau), d("render threshold in [-1, 1] (default: calibrated, "
                                             "stored in the model)", float_range=(-1.0, 1.0))),
            "publish_masks": (True, d("publish ~/masks")),
            "publish_overlay": (True, d("publish ~/overlay (computed only when subscribed)")),
            "publish_reconstruction": (True, d("publish ~/reconstruction (only when "
                                               "subscribed)")),
            "resolution_change_frames": (10, d(
                "frames of one new resolution in a row after which the node adopts it (the "
                "earlier ones are skipped)", int_range=(1, 10_000))),
        })
        # the inference settings: one name each, as InferenceConfig fields and CLI flags
        model_values = settings.values(cfg)
        self._declare({x.name: (model_values[x.name], d(
            x.doc + (f"; one of {', '.join(x.choices)}" if x.choices else "")
            + " (default: the model's)", int_range=x.range if x.type is int else None))
            for x in settings.exposed()})

    def _value(self, name: str):
        """A parameter's value; an array parameter left unset ([] by default) reads as []."""
        from rclpy.exceptions import ParameterUninitializedException

        try:
            return self.get_parameter(name).value
        except ParameterUninitializedException:
            return []

    def _apply(self, values: dict) -> None:
        """Validate a full parameter set and make it current (raises ConfigError)."""
        new = {**self.p, **values}
        inference = settings.apply(self.model.inference, new)  # ValueError naming a bad one
        self.model.check(inference)  # and one this model cannot run with
        roi = _parse_roi(new["roi"])
        polygon = _parse_polygon(new["bin_polygon"])
        floor = float(new["floor_depth"])
        plane = list(new["floor_plane"])
        if plane and (len(plane) != 3 or not all(math.isfinite(v) for v in plane)):
            raise ConfigError(f"floor_plane {plane} invalid; valid: [] (fit per frame) or "
                              "[a, b, c], three finite numbers")
        prep = replace(self.model.prep_cfg, roi=roi, polygon=polygon,
                       floor_depth=floor if floor > 0 else None,
                       floor_plane=tuple(plane) if plane else None,
                       min_height=float(new["min_height"]),
                       rim_band=float(new["rim_band"]), rim_step=float(new["rim_step"]))
        self.p, self.prep = new, prep
        self._roi_cache = {}

    def _on_set_parameters(self, params) -> SetParametersResult:
        values = {x.name: x.value for x in params if x.name in self._runtime_names}
        try:
            self._apply(values)
        except (ConfigError, ValueError) as e:
            return SetParametersResult(successful=False, reason=str(e))
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ frames
    def _skip(self, reason: str, message: str) -> None:
        self.counts["skipped"] += 1
        self.counts[f"skipped:{reason}"] += 1
        self.last_error = f"{reason}: {message}"
        # throttled per kind of problem: a camera repeating one fault logs it every 2 s, and a
        # different fault in between is still shown
        key, now = (reason, message[:40]), time.monotonic()
        if now - self._logged.get(key, -math.inf) >= 2.0:
            self._logged[key] = now
            self.get_logger().warning(f"frame skipped ({reason}): {message}")

    def _check_shape(self, shape: tuple[int, int]) -> None:
        if self._shape is None or shape == self._shape:
            self._shape, self._new_shape = shape, (None, 0)
            return
        seen, k = self._new_shape
        k = k + 1 if seen == shape else 1
        self._new_shape = (shape, k)
        if k >= self.p["resolution_change_frames"]:
            self.get_logger().warning(f"input resolution changed from {self._shape[1]}x"
                                      f"{self._shape[0]} to {shape[1]}x{shape[0]}: adopted")
            self._shape, self._new_shape = shape, (None, 0)
            return
        raise FrameError("resolution", f"{shape[1]}x{shape[0]} frame, but the stream is "
                                       f"{self._shape[1]}x{self._shape[0]}")

    def _prep_for(self, depth: np.ndarray):
        """The preprocessing config for this frame: the bin region of the stream's resolution,
        the per-side median of the regions found in its first `BIN_FRAMES` frames (until then,
        of those so far; `preprocess.node_defaults`). One frame can mislead the finder, and a
        region taken from it alone would cut every later frame wrongly."""
        from inseggan_ros.runtime.preprocess import BIN_FRAMES, median_region

        if self.prep.roi is not None or self.prep.polygon is not None:
            return self.prep
        found = self._roi_cache.setdefault(depth.shape, [])
        if len(found) < BIN_FRAMES:
            from inseggan_ros.runtime.preprocess import find_bin_roi

            found.append(find_bin_roi(depth))
            if len(found) == BIN_FRAMES:
                self.get_logger().info(
                    f"bin region: {list(median_region(found))} in the {depth.shape[1]}x"
                    f"{depth.shape[0]} frames (the median of the first {BIN_FRAMES} frames' "
                    "regions; set `roi` to fix it)")
        return replace(self.prep, roi=median_region(found))

    def _on_depth(self, msg: Image) -> None:
        t0 = time.perf_counter()
        self.counts["received"] += 1
        try:
            try:
                depth = conversions.depth_to_metres(msg)
            except image_codec.ImageFormatError as e:
                raise FrameError("encoding" if "encoding" in str(e) else "size", str(e)) from None
            self._check_shape(depth.shape)
            t1 = time.perf_counter()
            want_recon = self.p["publish_reconstruction"] and \
                self.pub_recon.get_subscription_count() > 0
            try:
                seg = self.model(depth, self._prep_for(depth), tau=self.p["tau"],
                                 reconstruction=want_recon, settings=self._settings())
            except ValueError as e:
                raise FrameError("depth", str(e)) from None
            t2 = time.perf_counter()
            labels_msg = conversions.numpy_to_image(seg.labels, "mono8", msg.header)
            self.pub_labels.publish(labels_msg)
            t3 = time.perf_counter()
        except FrameError as e:
            self._skip(e.reason, str(e))
            return
        except Exception as e:  # never die on a frame; count it and keep serving
            self._skip("internal", f"{type(e).__name__}: {e}")
            return
        self.counts["segmented"] += 1
        self.stamps.append(time.monotonic())
        self.latency_ms.append((t3 - t0) * 1e3)
        self.inference_ms.append((t2 - t1) * 1e3)
        conv = (t1 - t0) + (t3 - t2)
        t4 = time.perf_counter()
        self._publish_extras(msg, depth, seg)
        self.conversion_ms.append((conv + time.perf_counter() - t4) * 1e3)
        try:
            self._publish_picks(msg, depth, seg)
        except Exception as e:  # never die on a frame; the labels went out already
            self.pick_counts["skipped:internal"] += 1
            self.pick_problem = f"internal: {type(e).__name__}: {e}"
            self._warn_throttled("pick_internal", f"picks failed: {self.pick_problem}")

    def _publish_extras(self, msg: Image, depth: np.ndarray, seg) -> None:
        n = self.model.model_cfg.n_instances
        if self.p["publish_masks"] and self.pub_masks.get_subscription_count() > 0:
            masks = (seg.labels[..., None] == np.arange(1, n + 1, dtype=np.uint8))
            self.pub_masks.publish(conversions.numpy_to_image(
                masks.view(np.uint8) * np.uint8(255), f"8UC{n}", msg.header))
        if self.p["publish_overlay"] and self.pub_overlay.get_subscription_count() > 0:
            from inseggan_ros.core import viz

            self.pub_overlay.publish(conversions.numpy_to_image(
                viz.overlay(depth, seg.labels), "rgb8", msg.header))
        if seg.reconstruction is not None:
            self.pub_recon.publish(conversions.numpy_to_image(
                seg.reconstruction.astype(np.float32), "32FC1", msg.header))

    # ------------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        recent = [t for t in self.stamps if now - t <= 5.0]
        rate = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 1 and \
            recent[-1] > recent[0] else 0.0

        def pct(values, q):
            return f"{np.percentile(values, q):.2f}" if values else "nan"

        values = {
            "model": str(self.model_path), "device": str(self.model.device),
            "encoder_precision": self.model.resolve_precision(self.p["encoder_precision"]),
            "centre_precision": self.model.resolve_precision(self.p["centre_precision"]),
            "tau": f"{self.p['tau']:.3f}", "rate_hz": f"{rate:.2f}",
            "latency_p50_ms": pct(self.latency_ms, 50), "latency_p99_ms": pct(self.latency_ms, 99),
            "inference_p50_ms": pct(self.inference_ms, 50),
            "conversion_p50_ms": pct(self.conversion_ms, 50),
            "frames_received": str(self.counts["received"]),
            "frames_segmented": str(self.counts["segmented"]),
            "frames_skipped": str(self.counts["skipped"]),
        }
        for key in sorted(k for k in self.counts if k.startswith("skipped:")):
            values["frames_skipped_" + key.split(":", 1)[1]] = str(self.counts[key])
        values["last_error"] = self.last_error
        status = DiagnosticStatus(name=f"{self.get_name()}: instance segmentation",
                                  hardware_id=str(self.model_path))
        status.level, status.message = DiagnosticStatus.OK, "segmenting"
        if self.counts["segmented"] == 0:
            status.level, status.message = DiagnosticStatus.WARN, "no frame segmented yet"
        elif self.counts["skipped"]:
            status.level = DiagnosticStatus.WARN
            status.message = f"{self.counts['skipped']} frames skipped; last: {self.last_error}"
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        arr = DiagnosticArray(status=[status, self._picks_status()])
        arr.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(arr)

    def _picks_status(self) -> DiagnosticStatus:
        """The picks' own status: WARN with the reason while frames get no picks (no CameraInfo,
        a size mismatch), else OK with the last pick order."""
        status = DiagnosticStatus(name=f"{self.get_name()}: picks",
                                  hardware_id=str(self.model_path))
        values = {"camera_info_topic": self.sub_info.topic_name,
                  "camera_info_received": str(self.camera_info is not None).lower(),
                  "picks_published": str(self.pick_counts["published"]),
                  "last_picks": self.last_picks}
        for key in sorted(k for k in self.pick_counts if k.startswith("skipped:")):
            values["picks_skipped_" + key.split(":", 1)[1]] = str(self.pick_counts[key])
        if not self.get_parameter("publish_picks").value:
            status.level, status.message = DiagnosticStatus.OK, "off (publish_picks false)"
        elif self.pick_problem:
            status.level, status.message = DiagnosticStatus.WARN, self.pick_problem
        else:
            status.level, status.message = DiagnosticStatus.OK, "picking"
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        return status


def main(args=None) -> int:
    return common.run("segmenter", SegmenterNode, args, errors=(CheckpointError,))


if __name__ == "__main__":
    sys.exit(main())
