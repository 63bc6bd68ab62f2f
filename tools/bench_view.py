"""Does segmentation survive a tilted camera and an off-centre bin? Prints its figures.

    python -m tools.bench_view [--frames 40] [--tilts 5,10] [--model cylinder]

For each camera tilt it simulates `--frames` bins (RealSense D435-like 848 x 480 camera with its
noise preset, tilted, turned by `--roll`, the bin off-centre by `--offset`) and segments every
frame with the shipped model (`segment.Segmenter`) three ways:

  given    the true bin region and floor: the visible floor's bounding box
           (`preprocess.roi_from_camera`) and the simulator's floor plane;
  auto     nothing given: `preprocess.find_bin` on every frame (its box and floor plane);
  level    the region found as in auto, the floor as ONE depth (`estimate_floor`), as before
           the floor became a plane: what the plane gains;
  node     as the segmenter node runs with its defaults: the bin's bounding box found once, in
           the first frame (`find_bin_roi`), no outline, the floor plane fitted per frame.

It prints the mean mIoU (`metrics`, at the frame's resolution) of each, auto - given, the IoU of
the found floor outline (`polygon_from_camera`: the visible floor) and bounding box with the true
ones, and the preprocessing cost per frame (one OpenCV thread, median of repeated calls, at
1280 x 720) of the fixed path (region and plane given), the per-frame plane fit with a fixed
region (what the node does after finding the bin once) and the fully automatic path, as ratios
to the fixed path measured in the same run.
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace

import cv2
import numpy as np

from inseggan_ros.core.metrics import mean_miou, miou
from inseggan_ros.runtime.preprocess import (
    PreprocessConfig, estimate_floor, find_bin, fit_floor_plane, polygon_from_camera, prepare,
    roi_from_camera)
from inseggan_ros.sim.camera import get_camera
from inseggan_ros.sim.noise import get_noise
from inseggan_ros.sim.scene import BinSimulator, SceneConfig


def _mask(shape, polygon) -> np.ndarray:
    m = np.zeros(shape, np.uint8)
    cv2.fillPoly(m, [np.rint(np.asarray(polygon) * 256).astype(np.int32)], 1, shift=8)
    return m.astype(bool)


def _box_iou(a, b) -> float:
    ix = max(0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def _level_config(base: PreprocessConfig, depth: np.ndarray) -> PreprocessConfig:
    """The region found as `auto` does, the floor as one depth estimated in it."""
    found = find_bin(depth)
    x0, y0, x1, y1 = found.roi
    crop = depth[y0:y1, x0:x1]
    return replace(base, roi=found.roi, floor_plane=None,
                   floor_depth=estimate_floor(crop[crop > 0]))


def timing(cam, bin_cfg, frames: list[np.ndarray], base: PreprocessConfig,
           repeats: int = 50) -> dict:
    """Preprocessing ms per frame (median) of the fixed, plane-fit and automatic paths, and of
    the fit alone; the paths take turns call by call, so that a machine busy with other work
    slows them alike."""
    roi = roi_from_camera(cam, bin_cfg)
    fixed = replace(base, roi=roi, floor_depth=None, floor_plane=cam.floor_plane())
    fitted = replace(fixed, floor_plane=None)
    auto = replace(base, roi=None, polygon=None, floor_depth=None, floor_plane=None)
    paths = {"fixed": lambda d: prepare(d, fixed), "plane_fit": lambda d: prepare(d, fitted),
             "auto": lambda d: prepare(d, auto), "fit_only": lambda d: fit_floor_plane(d, roi)}
    times = {name: [] for name in paths}
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        for _ in range(repeats):
            for d in frames:
                for name, fn in paths.items():
                    t0 = time.perf_counter()
                    fn(d)
                    times[name].append(time.perf_counter() - t0)
    finally:
        cv2.setNumThreads(threads)
    return {name: 1000 * float(np.median(t)) for name, t in times.items()}


def run(frames: int = 40, tilts=(5.0, 10.0), roll: float = 2.0, offset=(-0.15, 0.08),
        model: str = "cylinder", obj: str = "cylinder", noise: str = "realsense", seed: int = 0,
        timing_size=(1280, 720), timing_frames: int = 3) -> dict:
    from inseggan_ros.core.paths import resolve_model
    from inseggan_ros.runtime.segment import Segmenter

    seg = Segmenter.from_checkpoint(resolve_model(model), device="cpu")
    base = replace(seg.prep_cfg, roi=None, polygon=None, floor_depth=None, floor_plane=None)
    results = {}
    for tilt in tilts:
        cam = replace(get_camera("realsense_d435"), tilt=float(tilt), roll=float(roll),
                      bin_offset=tuple(offset))
        cfg = SceneConfig(object=obj, instances=seg.model_cfg.n_instances,
                          camera=cam, noise=get_noise(noise))
        true_roi, true_poly = roi_from_camera(cam, cfg.bin), polygon_from_camera(cam, cfg.bin)
        given = replace(base, roi=true_roi, floor_plane=cam.floor_plane())
        true_mask = _mask((cam.height, cam.width), true_poly)
        scores = {"given": [], "auto": [], "level": [], "node": []}
        node = None
        region_iou, box_iou, failures = [], [], 0
        with BinSimulator(cfg) as sim:
            for k in range(frames):
                scene = sim.render(seed * 100_003 + k)
                scores["given"].append(miou(seg(scene.depth, given, reconstruction=False).labels,
                                            scene.labels))
                try:
                    found = find_bin(scene.depth)
                    region_iou.append(float((_mask(true_mask.shape, found.polygon) & true_mask)
                                            .sum() / (_mask(true_mask.shape, found.polygon)
                                                      | true_mask).sum()))
                    box_iou.append(_box_iou(found.roi, true_roi))
                    auto = seg(scene.depth, base, reconstruction=False).labels
                    level = seg(scene.depth, _level_config(base, scene.depth),
                                reconstruction=False).labels
                except ValueError:  # no bin found: the frame scores 0
                    failures += 1
                    auto = level = np.zeros_like(scene.labels)
                    region_iou.append(0.0)
                    box_iou.append(0.0)
                scores["auto"].append(miou(auto, scene.labels))
                scores["level"].append(miou(level, scene.labels))
                if k == 0:
                    try:
                        node = replace(base, roi=find_bin(scene.depth).roi)
                    except ValueError:
                        pass
                scores["node"].append(miou(seg(scene.depth, node, reconstruction=False).labels,
                                           scene.labels) if node is not None else 0.0)
        r = {name: mean_miou(v) for name, v in scores.items()}
        r.update(frames=frames, failures=failures, region_iou_mean=float(np.mean(region_iou)),
                 region_iou_min=float(np.min(region_iou)), box_iou_mean=float(np.mean(box_iou)),
                 box_iou_min=float(np.min(box_iou)), true_roi=true_roi)
        r["auto_minus_given"] = r["auto"] - r["given"]
        results[float(tilt)] = r
    if timing_frames > 0:
        cam = replace(get_camera("realsense_d435", *timing_size), tilt=float(max(tilts)),
                      roll=float(roll), bin_offset=tuple(offset))
        cfg = SceneConfig(object=obj, instances=seg.model_cfg.n_instances,
                          camera=cam, noise=get_noise(noise))
        with BinSimulator(cfg) as sim:
            depths = [sim.render(10_000 + k).depth for k in range(timing_frames)]
        t = timing(cam, cfg.bin, depths, base)
        t["size"] = f"{cam.width}x{cam.height}"
        results["timing"] = t
    return results


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.bench_view",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=40, help="simulated frames per tilt")
    ap.add_argument("--tilts", default="5,10", help="camera tilts, degrees (default 5,10)")
    ap.add_argument("--roll", type=float, default=2.0, help="camera roll, degrees")
    ap.add_argument("--offset", default="-0.15,0.08",
                    help="bin centre in the image, fraction of width,height from the centre")
    ap.add_argument("--model", default="cylinder", help="shipped model name or checkpoint")
    ap.add_argument("--object", default="cylinder", help="the object the model segments")
    ap.add_argument("--noise", default="realsense", help="noise preset (default realsense)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timing-frames", type=int, default=3,
                    help="1280x720 frames for the preprocessing timing (0 = skip)")
    a = ap.parse_args(argv)
    if a.frames < 1:
        ap.error(f"--frames {a.frames} invalid; valid: >= 1")
    try:
        tilts = tuple(float(t) for t in a.tilts.split(","))
        offset = tuple(float(t) for t in a.offset.split(","))
    except ValueError:
        ap.error("--tilts and --offset take numbers separated by commas, e.g. 5,10 and -0.15,0.08")
    if len(offset) != 2:
        ap.error(f"--offset {a.offset!r} invalid; valid: two fractions u,v")
    res = run(a.frames, tilts, a.roll, offset, a.model, a.object, a.noise, a.seed,
              timing_frames=a.timing_frames)
    print(f"model {a.model}, {a.frames} frames per tilt, 848x480 RealSense-like camera, roll "
          f"{a.roll} deg, bin offset {offset}, noise {a.noise}")
    print("| tilt | mIoU given | mIoU auto | auto - given | mIoU level floor | mIoU node | "
          "found outline IoU mean / min | found box IoU mean / min | no bin found |")
    print("|---|---|---|---|---|---|---|---|---|")
    for tilt, r in res.items():
        if tilt == "timing":
            continue
        print(f"| {tilt:g} | {r['given']:.3f} | {r['auto']:.3f} | {r['auto_minus_given']:+.3f} | "
              f"{r['level']:.3f} | {r['node']:.3f} | "
              f"{r['region_iou_mean']:.3f} / {r['region_iou_min']:.3f} | "
              f"{r['box_iou_mean']:.3f} / {r['box_iou_min']:.3f} | {r['failures']} |")
    if "timing" in res:
        t = res["timing"]
        print(f"preprocessing per frame at {t['size']} (one OpenCV thread, median): fixed "
              f"(region and plane given) {t['fixed']:.2f} ms; plane fitted per frame "
              f"{t['plane_fit']:.2f} ms ({t['plane_fit'] / t['fixed']:.2f}x; the fit alone "
              f"{t['fit_only']:.2f} ms); fully automatic {t['auto']:.2f} ms "
              f"({t['auto'] / t['fixed']:.2f}x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
