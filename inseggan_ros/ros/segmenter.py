r"""segmenter: depth frames in, instance labels, masks and picks out (InSeGAN, a trained model).

    ros2 run inseggan_ros segmenter                                  # the shipped default model
    ros2 run inseggan_ros segmenter --ros-args \
        -r camera/depth/image_rect_raw:=/camera/camera/depth/image_rect_raw \
        -p model_path:=models/cylinder/model.pt -p roi:=[58,58,166,166]

A managed (lifecycle) node: configure loads the model, activate subscribes, deactivate stops the
work, cleanup unloads the model; with `autostart` (the default) it configures and activates
itself at start, as a plain node. Transitions: the standard ~/change_state and ~/get_state
services (lifecycle_msgs). Services (std_srvs):
    ~/enable        SetBool: false pauses the work (the model stays loaded), true resumes it
    ~/segment_next  Trigger: segments the next frame that arrives after the call (paused too),
                    publishes its results and answers 'instances <n>, picks <m>'
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
and in `target_frame` (default: the input's frame), with the input's stamp:
    ~/picks               geometry_msgs/PoseArray, one pose per instance in pick order
                          (picks.py: free ones first, then the top-most): position = its
                          visible surface's centroid, orientation's z axis = the surface
                          normal there (only when ~/picks, ~/pick_confidence or ~/markers is
                          subscribed, or for ~/segment_next)
    ~/pick_confidence     std_msgs/Float32MultiArray, each pick's instance fit in [0, 1], in
                          the same order (its dimension's label: the stamp, '<sec>.<nanosec>')
    ~/markers             visualization_msgs/MarkerArray for RViz: normal arrows and ranks
    /diagnostics          diagnostic_msgs/DiagnosticArray: rate, latency and its stages, error
                          counters; '<node>: picks' (WARN while CameraInfo is missing or of
                          another size); '<node>: bin' (the frames' label-free measures against
                          the model card's: WARN when the bin does not look like the model's
                          part, or is empty)
A bad frame (encoding, size, empty, no valid depth, a resolution change) is logged (throttled),
counted in diagnostics and skipped; the node keeps serving. A missing or incompatible model
stops an autostarting node at start-up with one clear error line (else configure fails with it).
Unless FASTRTPS_DEFAULT_PROFILES_FILE is set, the node uses the shipped Fast DDS profile for
large frames (common.py).
"""
from __future__ import annotations

import copy
import math
import sys
import time
from collections import Counter, deque
from dataclasses import dataclass, replace

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from rclpy.qos import QoSHistoryPolicy, qos_profile_sensor_data
from rclpy.task import Future
from sensor_msgs.msg import Image
from std_srvs.srv import SetBool, Trigger

from inseggan_ros.core import image_codec
from inseggan_ros.core import settings
from inseggan_ros.core.checkpoint import CheckpointError
from inseggan_ros.core.paths import NotFoundError
from inseggan_ros.ros import common
from inseggan_ros.ros import conversions
from inseggan_ros.ros import segmenter_params as params

# DEFAULT_MODEL and resolve_model are imported from here by the tests and bench_node
from inseggan_ros.core.paths import DEFAULT_MODEL, resolve_model  # noqa: F401
from inseggan_ros.ros.common import ConfigError, FrameError

SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE
# the stages of a frame's latency, in order (/diagnostics: stage_<name>_p50_ms)
STAGES = ("preprocess", "network", "labels", "picks", "publish")
COMPRESSED_SUFFIX = "/compressedDepth"


@dataclass
class _Request:
    """A ~/segment_next call waiting for the next frame that arrives after it."""

    since_ns: int  # wall clock (the DDS receive stamps' clock) when it was called
    future: Future


class SegmenterNode(LifecycleNode):
    def __init__(self, **kwargs):
        super().__init__("segmenter", **kwargs)
        common.declare(self, params.startup())
        common.declare(self, params.target())
        self.model = self.sub = self.picks = None
        self._set_target({n: self._value(n) for n in params.TARGET_NAMES}, startup=True)
        self.add_on_set_parameters_callback(self._on_set_target)
        self.publishers_out = {}
        self._runtime_names = None  # declared on the first configure (the model's defaults)
        self.enabled, self._requests = True, []
        self._autostarting, self._configure_error = False, None
        self._reset_counts()
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_service(SetBool, "~/enable", self._on_enable)
        # its own reentrant group: the call waits (a coroutine) for the next frame, and a
        # waiting callback holds its group; the frames and the timeout run meanwhile
        self._waiting_group = ReentrantCallbackGroup()
        self.create_service(Trigger, "~/segment_next", self._on_segment_next,
                            callback_group=self._waiting_group)
        self.create_timer(self.get_parameter("diagnostics_period").value, self._publish_diagnostics)
        if self.get_parameter("autostart").value:
            self._autostart()

    def _autostart(self) -> None:
        """Configure and activate now; a failure to configure raises its error (one line)."""
        self._autostarting = True
        try:
            if self.trigger_configure() != SUCCESS:
                raise self._configure_error or ConfigError("configure failed")
            if self.trigger_activate() != SUCCESS:
                raise ConfigError("activate failed")
        finally:
            self._autostarting = False

    def _reset_counts(self) -> None:
        window = self.get_parameter("latency_window").value
        self.counts = Counter()  # received, segmented, paused, skipped and skipped:<reason>
        self.latency_ms = deque(maxlen=window)  # received -> labels published
        self.total_ms = deque(maxlen=window)  # received -> every output published
        self.inference_ms = deque(maxlen=window)  # segment.Segmenter call alone
        self.conversion_ms = deque(maxlen=window)  # message decode + encode
        self.stage_ms = {s: deque(maxlen=window) for s in STAGES}
        self.stamps = deque(maxlen=1000)  # monotonic time of each segmented frame
        self.pick_counts = Counter()  # published, skipped:<reason>
        self.pick_problem = ""  # why the last frame got no picks ('' = it got them)
        self.last_picks = ""  # the last published pick order, for /diagnostics
        self.last_error = ""
        self._logged = {}  # (reason, message start) -> when last logged
        self._shape = None  # resolution of the last good frame
        self._new_shape = (None, 0)  # (shape, consecutive frames) of a changed resolution
        self._roi_cache = {}  # frame shape -> the bin regions found in its first frames
        self.bin_check, self._bin_level = None, "ok"

    # ------------------------------------------------------------------ lifecycle
    def on_configure(self, state) -> TransitionCallbackReturn:
        try:
            self._configure()
        except Exception as e:  # a bad model or parameter: back to unconfigured, say why
            self._unload()
            self._configure_error = e
            if not self._autostarting:
                known = isinstance(e, (ConfigError, NotFoundError, CheckpointError))
                self.get_logger().error(f"configure failed: {e}" if known else
                                        f"configure failed: {type(e).__name__}: {e}")
            return FAILURE
        return super().on_configure(state)

    def _configure(self) -> None:
        """Load the model, apply the parameters, warm the model up, make the publishers."""
        self.model_path = resolve_model(self.get_parameter("model_path").value)
        device = self.get_parameter("device").value
        if device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"parameter device={device!r} invalid; valid: auto, cpu, cuda")
        transport = self.get_parameter("input_transport").value
        if transport not in ("raw", "compressedDepth"):
            raise ConfigError(f"parameter input_transport={transport!r} invalid; valid: raw, "
                              "compressedDepth")
        import torch

        torch.set_num_threads(self.get_parameter("threads").value)
        from inseggan_ros.runtime.bin_check import BinCheck, card_reference
        from inseggan_ros.runtime.segment import Segmenter as Model

        try:
            model = Model.from_checkpoint(
                self.model_path, device=device,
                superpixel_thread=self.get_parameter("superpixel_thread").value)
            model.traced = True  # the networks as traced graphs: the same numbers, sooner
        except ValueError as e:  # e.g. cuda asked for but not available
            raise ConfigError(f"parameter device={device!r}: {e}") from None
        # a training checkpoint stores no settings: it runs with realtime.yaml's, as every
        # exported model starts with, and a parameters file applies over those
        model.inference = settings.file_base(model.inference, model.stored_settings)
        self.model, self.p = model, {}
        if self._runtime_names is None:
            self._runtime_names, specs = params.runtime(model)
            common.declare(self, specs)
            self.add_on_set_parameters_callback(self._on_set_parameters)
        try:
            self._apply({name: self._value(name) for name in self._runtime_names})
        except ValueError as e:
            raise ConfigError(str(e)) from None
        self._reset_counts()
        self._warm_up()
        self.bin_check = BinCheck(*card_reference(self.model_path), model.model_cfg.n_instances,
                                  window=self.get_parameter("bin_check_window").value)
        self._make_publishers()
        n = model.model_cfg.n_instances
        self.get_logger().info(f"model {self.model_path} ({n} x instances, tau {model.tau:.3f}, "
                               f"device {model.device}); bin check: {self.bin_check.source}")

    def _make_publishers(self) -> None:
        from inseggan_ros.ros.pick_output import PickOutput

        self.publishers_out = {name: self.create_lifecycle_publisher(Image, f"~/{name}", 5)
                               for name in ("labels", "masks", "overlay", "reconstruction")}
        self.picks = PickOutput(self, {
            "normal_radius": self.get_parameter("pick_normal_radius").value,
            "free_rise": self.get_parameter("pick_free_rise").value},
            self.get_parameter("use_tf").value)
        self.picks.set_target(*self._target)

    def _unload(self) -> None:
        for pub in self.publishers_out.values():
            self.destroy_lifecycle_publisher(pub)
        self.publishers_out = {}
        if self.picks is not None:
            self.picks.destroy()
        self.model = self.picks = None

    def on_activate(self, state) -> TransitionCallbackReturn:
        qos = copy.copy(qos_profile_sensor_data)  # rclpy's profile is shared: change a copy
        qos.history, qos.depth = QoSHistoryPolicy.KEEP_LAST, 1
        compressed = self.get_parameter("input_transport").value == "compressedDepth"
        if compressed:
            from sensor_msgs.msg import CompressedImage

            topic = self.resolve_topic_name(common.DEPTH_TOPIC) + COMPRESSED_SUFFIX
            self.sub = self.create_subscription(CompressedImage, topic, self._on_depth, qos)
        else:
            self.sub = self.create_subscription(Image, common.DEPTH_TOPIC, self._on_depth, qos)
        if self.resolve_topic_name("depth") != self.resolve_topic_name("depth", only_expand=True):
            self.get_logger().warning(  # the name this node subscribed to before
                f"the remap of 'depth' has no effect: the depth topic is {common.DEPTH_TOPIC} "
                f"(remap that name: -r {common.DEPTH_TOPIC}:=/your/depth/topic)")
        self.picks.subscribe(self._camera_info_topic(compressed), qos)
        self.get_logger().info(f"listening on {self.sub.topic_name} (camera info: "
                               f"{self.picks.sub_info.topic_name})")
        return super().on_activate(state)

    def _unsubscribe(self, why: str) -> None:
        if self.sub is not None:
            self.destroy_subscription(self.sub)
            self.sub = None
        if self.picks is not None:
            self.picks.unsubscribe()
        for r in self._requests:
            if not r.future.done():
                r.future.set_result((False, why))

    def on_deactivate(self, state) -> TransitionCallbackReturn:
        self._unsubscribe("the node was deactivated")
        return super().on_deactivate(state)

    def on_cleanup(self, state) -> TransitionCallbackReturn:
        self._unload()
        return super().on_cleanup(state)

    def on_shutdown(self, state) -> TransitionCallbackReturn:
        self._unsubscribe("the node is shutting down")
        self._unload()
        return super().on_shutdown(state)

    def on_error(self, state) -> TransitionCallbackReturn:
        self._unsubscribe("the node is recovering from an error")
        self._unload()
        return SUCCESS  # back to unconfigured

    def _state(self) -> str:
        return self._state_machine.current_state[1]

    # ------------------------------------------------------------------ services
    def _on_enable(self, request, response):
        self.enabled = bool(request.data)
        response.success = True
        response.message = ("streaming: every frame is segmented" if self.enabled else
                            "paused: frames are not segmented (~/segment_next still works); "
                            "the model stays loaded")
        self.get_logger().info(response.message)
        return response

    async def _on_segment_next(self, request, response):
        """Wait (without blocking the executor) for the next frame that arrives after the
        call; answer with its instance and pick counts."""
        if self.model is None or self.sub is None:
            response.success = False
            response.message = (f"no model loaded (lifecycle state {self._state()}): configure "
                                "and activate the node first" if self.model is None else
                                f"not subscribed (lifecycle state {self._state()}): activate "
                                "the node first")
            return response
        future = Future()
        req = _Request(time.time_ns(), future)
        self._requests.append(req)
        timeout = self.get_parameter("segment_next_timeout").value
        topic = self.sub.topic_name

        def expire():
            if not future.done():
                future.set_result((False, f"no frame arrived on {topic} within {timeout:g} s "
                                          "(segment_next_timeout)"))
        timer = self.create_timer(timeout, expire, callback_group=self._waiting_group)
        try:
            response.success, response.message = await future
        finally:
            self.destroy_timer(timer)
            self._requests.remove(req)
        return response

    # ------------------------------------------------------------------ picks
    def _camera_info_topic(self, compressed: bool = False) -> str:
        """camera_info beside the depth topic (as image_transport pairs them): when only the
        depth topic is remapped, the camera_info of the same folder; a remap of
        camera/depth/camera_info itself wins."""
        info = self.resolve_topic_name(common.CAMERA_INFO_TOPIC)
        if info != self.resolve_topic_name(common.CAMERA_INFO_TOPIC, only_expand=True):
            return info  # remapped explicitly
        depth = self.sub.topic_name
        if compressed and depth.endswith(COMPRESSED_SUFFIX):
            depth = depth[:-len(COMPRESSED_SUFFIX)]
        return depth.rsplit("/", 1)[0] + "/camera_info"

    def _publish_picks(self, msg, depth: np.ndarray, seg, forced: bool) -> int | None:
        """Picks of a segmented frame on ~/picks, ~/pick_confidence and ~/markers (when
        subscribed, or `forced`) -> how many, or None when there are none to give. Any
        problem (no or mismatched CameraInfo, no transform) is counted, shown in /diagnostics
        and logged (throttled); the labels were published already."""
        if not self.get_parameter("publish_picks").value:
            return None
        try:
            if not forced and not self.picks.subscribed():
                self.picks.camera_matrix(depth.shape)  # a problem still shows in diagnostics
                self.pick_problem = ""
                return None
            picks, confidence = self.picks.compute(msg.header, depth, seg, self.p["tau"],
                                                   self.model.prep_cfg.max_height)
        except FrameError as e:
            self.pick_counts[f"skipped:{e.reason}"] += 1
            self.pick_problem = str(e)
            self._warn_throttled(e.reason, str(e))
            return None
        self.pick_problem = ""
        self.picks.publish(msg.header, picks, confidence)
        self.pick_counts["published"] += 1
        self.last_picks = " ".join(f"#{p.instance}{'' if p.free else '(under)'}:{c:.2f}"
                                   for p, c in zip(picks, confidence))
        return len(picks)

    def _warn_throttled(self, reason: str, message: str, period: float = 5.0) -> None:
        key, now = ("warn", reason), time.monotonic()
        if now - self._logged.get(key, -math.inf) >= period:
            self._logged[key] = now
            self.get_logger().warning(message)

    def _warm_up(self) -> None:
        """Inference on a synthetic input before subscribing, so that the first real frame
        does not pay PyTorch's one-time set-up (the demo's first frame took 1.7 s without),
        nor the tracing of the networks' graphs and TorchScript's first, profiling runs."""
        s = self.model.prep_cfg.size
        x = np.full((1, 1, s, s), -1.0, np.float32)
        x[0, 0, s // 4:s // 2, s // 4:3 * s // 4] = 0.0  # one flat object
        for _ in range(3):
            self.model.segment_batch(x, settings=self._settings())

    def _settings(self):
        """The model's test-time settings (`InferenceConfig`) as the parameters now set them."""
        return settings.apply(self.model.inference, self.p)

    # ------------------------------------------------------------------ parameters
    def _value(self, name: str):
        """A parameter's value; an array parameter left unset ([] by default) reads as []."""
        from rclpy.exceptions import ParameterUninitializedException

        try:
            return self.get_parameter(name).value
        except ParameterUninitializedException:
            return []

    def _set_target(self, values: dict, startup: bool = False) -> None:
        """Validate the target frame and transform and make them current (ConfigError)."""
        current = {} if startup else {n: self._value(n) for n in params.TARGET_NAMES}
        self._target = params.check_target({**current, **values})
        if self._target[0] and self.get_parameter("use_tf").value:
            self._target = (self._target[0], None, None)  # looked up in tf per frame
        if self.picks is not None:
            self.picks.set_target(*self._target)

    def _on_set_target(self, parameters) -> SetParametersResult:
        values = {x.name: x.value for x in parameters if x.name in params.TARGET_NAMES}
        if values:
            try:
                self._set_target(values)
            except ConfigError as e:
                return SetParametersResult(successful=False, reason=str(e))
        return SetParametersResult(successful=True)

    def _apply(self, values: dict) -> None:
        """Validate a full parameter set and make it current (raises ConfigError)."""
        new = {**self.p, **values}
        inference = settings.apply(self.model.inference, new)  # ValueError naming a bad one
        self.model.check(inference)  # and one this model cannot run with
        roi = params.parse_roi(new["roi"])
        polygon = params.parse_polygon(new["bin_polygon"])
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

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        values = {x.name: x.value for x in parameters if x.name in self._runtime_names}
        if not values or self.model is None:  # unconfigured: checked at the next configure
            return SetParametersResult(successful=True)
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

    def _on_depth(self, msg, info) -> None:
        t0 = time.perf_counter()
        arrived = (info or {}).get("received_timestamp") or time.time_ns()
        self.counts["received"] += 1
        waiting = [r for r in self._requests if r.since_ns < arrived and not r.future.done()]
        if not self.enabled and not waiting:
            self.counts["paused"] += 1
            return
        try:
            outcome = self._process(msg, t0, forced=bool(waiting))
        except FrameError as e:
            self._skip(e.reason, str(e))
            outcome = (False, f"frame skipped ({e.reason}): {e}")
        except Exception as e:  # never die on a frame; count it and keep serving
            self._skip("internal", f"{type(e).__name__}: {e}")
            outcome = (False, f"frame skipped (internal): {type(e).__name__}: {e}")
        for r in waiting:
            r.future.set_result(outcome)

    def _segment(self, msg, stages: dict):
        """Decode and segment a frame -> (depth in metres, Segmentation); FrameError."""
        t0 = time.perf_counter()
        try:
            if isinstance(msg, Image):
                depth = conversions.depth_to_metres(msg)
            else:
                depth = conversions.depth_to_metres(msg)
        except image_codec.ImageFormatError as e:
            reason = "encoding" if "encoding" in str(e) else \
                "size" if isinstance(msg, Image) else "compressed"
            raise FrameError(reason, str(e)) from None
        self._check_shape(depth.shape)
        t1 = time.perf_counter()
        want_recon = self.p["publish_reconstruction"] and \
            self.publishers_out["reconstruction"].get_subscription_count() > 0
        try:
            seg = self.model(depth, self._prep_for(depth), tau=self.p["tau"],
                             reconstruction=want_recon, settings=self._settings(),
                             timings=stages)
        except ValueError as e:
            raise FrameError("depth", str(e)) from None
        stages["decode"] = t1 - t0
        stages["inference"] = time.perf_counter() - t1
        return depth, seg

    def _process(self, msg, t0: float, forced: bool) -> tuple[bool, str]:
        """Segment a frame and publish what it gives -> (True, 'instances n, picks m')."""
        stages = {}
        depth, seg = self._segment(msg, stages)
        t2 = time.perf_counter()
        self.publishers_out["labels"].publish(
            conversions.numpy_to_image(seg.labels, "mono8", msg.header))
        t3 = time.perf_counter()
        self.counts["segmented"] += 1
        self.stamps.append(time.monotonic())
        self.latency_ms.append((t3 - t0) * 1e3)
        self._publish_extras(msg, depth, seg)
        empty = self._check_bin(seg)
        t4 = time.perf_counter()
        try:
            n_picks = self._publish_picks(msg, depth, seg, forced)
        except Exception as e:  # never die on a frame; the labels went out already
            n_picks = None
            self.pick_counts["skipped:internal"] += 1
            self.pick_problem = f"internal: {type(e).__name__}: {e}"
            self._warn_throttled("pick_internal", f"picks failed: {self.pick_problem}")
        t5 = time.perf_counter()
        self._record(stages, t0, t2, t3, t4, t5)
        if not forced:
            return True, ""
        import cv2

        counts = cv2.calcHist([seg.labels], [0], None, [256], [0, 256]).ravel()[1:]
        text = f"instances {int((counts > 0).sum())}, picks {n_picks or 0}"
        if n_picks is None:
            text += f" ({self.pick_problem or 'picks off'})"
        return True, text + ("; the bin is empty" if empty else "")

    def _record(self, stages: dict, t0, t2, t3, t4, t5) -> None:
        """The frame's times: received (t0) -> segmented (t2) -> labels published (t3) ->
        extras published (t4) -> picks published (t5)."""
        self.stage_ms["preprocess"].append((stages["decode"] + stages["preprocess"]) * 1e3)
        self.stage_ms["network"].append(stages["network"] * 1e3)
        self.stage_ms["labels"].append(stages["labels"] * 1e3)
        self.stage_ms["picks"].append((t5 - t4) * 1e3)
        self.stage_ms["publish"].append((t4 - t2) * 1e3)
        self.total_ms.append((t5 - t0) * 1e3)
        self.inference_ms.append(stages["inference"] * 1e3)
        self.conversion_ms.append((stages["decode"] + t4 - t2) * 1e3)

    def _check_bin(self, seg) -> bool:
        """The frame's label-free measures into the bin check -> whether the bin is empty."""
        from inseggan_ros.runtime.bin_check import label_free

        m = label_free(seg.x64[None], seg.fg64[None], seg.renders64[None],
                       seg.reconstruction64[None], seg.labels64[None], self.p["tau"])
        self.bin_check.add(m)
        return m["coverage"] is None

    def _publish_extras(self, msg, depth: np.ndarray, seg) -> None:
        n = self.model.model_cfg.n_instances
        out = self.publishers_out
        if self.p["publish_masks"] and out["masks"].get_subscription_count() > 0:
            masks = (seg.labels[..., None] == np.arange(1, n + 1, dtype=np.uint8))
            out["masks"].publish(conversions.numpy_to_image(
                masks.view(np.uint8) * np.uint8(255), f"8UC{n}", msg.header))
        if self.p["publish_overlay"] and out["overlay"].get_subscription_count() > 0:
            from inseggan_ros.core import viz

            out["overlay"].publish(conversions.numpy_to_image(
                viz.overlay(depth, seg.labels), "rgb8", msg.header))
        if seg.reconstruction is not None:
            out["reconstruction"].publish(conversions.numpy_to_image(
                seg.reconstruction.astype(np.float32), "32FC1", msg.header))

    # ------------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self) -> None:
        from inseggan_ros.ros.segmenter_diagnostics import statuses

        arr = DiagnosticArray(status=statuses(self))
        bin_status = arr.status[-1]
        level = "warn" if bin_status.level != DiagnosticStatus.OK else "ok"
        if level != self._bin_level and self.bin_check is not None:
            # one call site per severity: rclpy refuses a call site whose severity changes
            if level == "warn":
                self.get_logger().warning(f"bin check: {bin_status.message}")
            else:
                self.get_logger().info(f"bin check: {bin_status.message}")
        self._bin_level = level
        arr.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(arr)


def main(args=None) -> int:
    return common.run("segmenter", SegmenterNode, args, errors=(CheckpointError,))


if __name__ == "__main__":
    sys.exit(main())
