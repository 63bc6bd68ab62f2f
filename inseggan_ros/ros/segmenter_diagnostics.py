"""The segmenter's /diagnostics statuses: the segmentation (state, rate, latency and its stages,
frame counters), the picks (CameraInfo, counters) and the bin (the frames' label-free measures
against the model card's, `bin_check.BinCheck`)."""
from __future__ import annotations

import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

LEVELS = {"ok": DiagnosticStatus.OK, "warn": DiagnosticStatus.WARN}


def _pct(values, q) -> str:
    return f"{np.percentile(values, q):.2f}" if values else "nan"


def _status(node, what: str, level, message: str, values: dict) -> DiagnosticStatus:
    status = DiagnosticStatus(name=f"{node.get_name()}: {what}",
                              hardware_id=str(getattr(node, "model_path", "")))
    status.level, status.message = level, message
    status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
    return status


def _timing_values(node) -> dict:
    now = time.monotonic()
    recent = [t for t in node.stamps if now - t <= 5.0]
    rate = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 1 and \
        recent[-1] > recent[0] else 0.0
    values = {"rate_hz": f"{rate:.2f}",
              "latency_p50_ms": _pct(node.latency_ms, 50),
              "latency_p99_ms": _pct(node.latency_ms, 99),
              "total_p50_ms": _pct(node.total_ms, 50), "total_p99_ms": _pct(node.total_ms, 99),
              "inference_p50_ms": _pct(node.inference_ms, 50),
              "conversion_p50_ms": _pct(node.conversion_ms, 50)}
    values["total_mean_ms"] = f"{np.mean(node.total_ms):.2f}" if node.total_ms else "nan"
    for stage, times in node.stage_ms.items():
        values[f"stage_{stage}_p50_ms"] = _pct(times, 50)
        values[f"stage_{stage}_mean_ms"] = f"{np.mean(times):.2f}" if times else "nan"
    return values


def segmentation_status(node) -> DiagnosticStatus:
    """OK while segmenting, paused or not active; WARN before the first frame and once frames
    have been skipped; ERROR when the last configure failed."""
    state = node._state()
    values = {"lifecycle_state": state, "enabled": str(node.enabled).lower()}
    model = node.model
    if model is not None:
        values.update({
            "model": str(node.model_path), "device": str(model.device),
            "encoder_precision": model.resolve_precision(node.p["encoder_precision"]),
            "centre_precision": model.resolve_precision(node.p["centre_precision"]),
            "tau": f"{node.p['tau']:.3f}"})
    values.update(_timing_values(node))
    c = node.counts
    values.update({"frames_received": c["received"], "frames_segmented": c["segmented"],
                   "frames_paused": c["paused"], "frames_skipped": c["skipped"]})
    for key in sorted(k for k in c if k.startswith("skipped:")):
        values["frames_skipped_" + key.split(":", 1)[1]] = c[key]
    values["last_error"] = node.last_error
    OK, WARN = DiagnosticStatus.OK, DiagnosticStatus.WARN
    if model is None:
        error = node._configure_error
        level, message = (DiagnosticStatus.ERROR, f"configure failed: {error}") if error else \
            (OK, f"{state}: no model loaded")
    elif node.sub is None:
        level, message = OK, f"{state}: not subscribed"
    elif not node.enabled:
        level, message = OK, "paused (~/enable false): frames are not segmented"
    elif c["segmented"] == 0:
        level, message = WARN, "no frame segmented yet"
    elif c["skipped"]:
        level, message = WARN, f"{c['skipped']} frames skipped; last: {node.last_error}"
    else:
        level, message = OK, "segmenting"
    return _status(node, "instance segmentation", level, message, values)


def picks_status(node) -> DiagnosticStatus:
    """WARN with the reason while frames get no picks (no CameraInfo, a size mismatch, no
    transform), else OK with the last pick order."""
    out = node.picks
    values = {"camera_info_topic": out.sub_info.topic_name if out and out.sub_info else "",
              "camera_info_received": str(out is not None and out.camera_info is not None
                                          ).lower(),
              "target_frame": node._target[0] or "(the depth image's)",
              "picks_published": str(node.pick_counts["published"]),
              "last_picks": node.last_picks}
    for key in sorted(k for k in node.pick_counts if k.startswith("skipped:")):
        values["picks_skipped_" + key.split(":", 1)[1]] = str(node.pick_counts[key])
    if not node.get_parameter("publish_picks").value:
        level, message = DiagnosticStatus.OK, "off (publish_picks false)"
    elif node.pick_problem:
        level, message = DiagnosticStatus.WARN, node.pick_problem
    else:
        level, message = DiagnosticStatus.OK, "picking"
    return _status(node, "picks", level, message, values)


def bin_status(node) -> DiagnosticStatus:
    """The bin check's verdict: OK, or WARN when the recent frames' measures leave the card's
    range or the last frame was an empty bin; 'no reference' where the card has no measures."""
    if node.bin_check is None:
        return _status(node, "bin", DiagnosticStatus.OK, "no model loaded", {})
    verdict = node.bin_check.verdict()
    return _status(node, "bin", LEVELS[verdict.level], verdict.message, verdict.values)


def statuses(node) -> list[DiagnosticStatus]:
    return [segmentation_status(node), picks_status(node), bin_status(node)]
