"""Pick benchmark (`python -m tools.bench_picks`): the picks the segmenter's labels give,
against the simulator's truth, on simulated bins (no ROS).

The simulator knows every pose, so per instance the truth is:
  * its visible surface's centroid: `picks.compute_picks` on the noise-free depth and the true
    labels (the same definition, on perfect input);
  * the surface normal there, from its pose: the cylinder's side is normal to its axis, its caps
    along it (at the surface point nearest that centroid; within RIM of a cap's edge the normal
    is undefined and the instance is left out of the normal figure);
  * the surface normal at the point the pick names (the true instance's surface point nearest
    the predicted centroid): what a suction cup placed there meets. On a curved part a centroid
    that lands off the true one turns the true normal with it; this second figure tells that
    (counted in the centroid error) from an error of the fitted plane itself;
  * how much of it is hidden: each instance rendered alone (the others moved away) against what
    shows of it in the scene; free = at most FREE_TRUE of it hidden.
Predicted instances are matched to true ones by mask IoU (Hungarian, IoU >= 0.5). Printed:
centroid and normal errors of the matched instances more than half visible, and how often the
top pick is a truly free instance (the true instance more than half of its pixels belong to:
an instance the model cut short still counts as itself).
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

FREE_TRUE = 0.02  # hidden fraction up to which an instance counts as free in the truth
RIM = 0.0015  # metres from a cap's edge within which the true normal is left undefined
MATCH_IOU = 0.5


def camera_to_world(cam) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with world = R @ camera + t for `sim.camera.CameraConfig` (its x along world x,
    y along world -y, z down, at mount_height above the floor)."""
    return np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, cam.mount_height])


def object_bodies(sim) -> list[int]:
    """The pybullet bodies of the scene's objects in label order (label k = the k-th; the
    static bin parts have no mass)."""
    p, c = sim.p, sim.client
    ids = sorted(p.getBodyUniqueId(i, physicsClientId=c)
                 for i in range(p.getNumBodies(physicsClientId=c)))
    return [b for b in ids if p.getDynamicsInfo(b, -1, physicsClientId=c)[0] > 0]


def hidden_fractions(sim, labels: np.ndarray) -> np.ndarray:
    """(n,) the share of each instance's own silhouette (rendered alone) that does not show
    in the scene's labels: 0 = nothing on it. Leaves the bodies where they were."""
    p, c, cam = sim.p, sim.client, sim.cfg.camera
    bodies = object_bodies(sim)
    poses = [p.getBasePositionAndOrientation(b, physicsClientId=c) for b in bodies]
    out = np.zeros(len(bodies))
    try:
        for b in bodies:  # out of the view, in turn
            p.resetBasePositionAndOrientation(b, [10, 10, -10], [0, 0, 0, 1], physicsClientId=c)
        for k, b in enumerate(bodies):
            p.resetBasePositionAndOrientation(b, *poses[k], physicsClientId=c)
            seg = np.asarray(p.getCameraImage(cam.width, cam.height, sim._view, sim._proj,
                                              shadow=0, renderer=p.ER_TINY_RENDERER,
                                              physicsClientId=c)[4]).reshape(cam.height, cam.width)
            alone = int((seg == b).sum())
            out[k] = 1 - (labels == k + 1).sum() / alone if alone else 1.0
            p.resetBasePositionAndOrientation(b, [10, 10, -10], [0, 0, 0, 1], physicsClientId=c)
    finally:
        for b, pose in zip(bodies, poses):
            p.resetBasePositionAndOrientation(b, *pose, physicsClientId=c)
    return np.clip(out, 0, 1)


def cylinder_normal(point_cam, pose, cam, radius: float, height: float):
    """The outward normal (camera frame) of a cylinder (axis z, centred) with `pose` (x, y, z,
    qx, qy, qz, qw; world) at its surface point `point_cam`; None within RIM of a cap's edge."""
    from scipy.spatial.transform import Rotation

    Rc, tc = camera_to_world(cam)
    Ro = Rotation.from_quat(pose[3:7]).as_matrix()
    q = Ro.T @ (Rc @ point_cam + tc - pose[:3])
    radial = np.hypot(q[0], q[1])
    cap = abs(abs(q[2]) - height / 2)
    side = abs(radial - radius)
    if min(cap, side) > 0.003 or (radial > radius - RIM and abs(q[2]) > height / 2 - RIM):
        return None  # not on the surface (a bad match) or at a rim
    n = np.array([0, 0, np.sign(q[2])]) if cap < side else np.array([q[0], q[1], 0]) / radial
    return Rc.T @ (Ro @ n)


def scene_truth(sim, scene, clean_depth: np.ndarray) -> dict:
    """The truth of one rendered scene: per instance (label k + 1 at index k) the surface
    centroid, the normal there (NaN where undefined), the hidden fraction and the mask."""
    from inseggan_ros.runtime.picks import compute_picks, points

    cam, spec = sim.cfg.camera, sim.spec
    n = len(scene.poses)
    hidden = hidden_fractions(sim, scene.labels)
    centroid = np.full((n, 3), np.nan)
    normal = np.full((n, 3), np.nan)
    truth = {"centroid": centroid, "normal": normal, "hidden": hidden, "labels": scene.labels,
             "normal_at": None}
    if spec.name == "cylinder":
        r = float(np.abs(spec.mesh.vertices[:, :2]).max())
        h = float(np.ptp(spec.mesh.vertices[:, 2]))
        surface = points(clean_depth, cam.K)  # once a scene: normal_at runs for every pick
        valid = clean_depth > 0

        def normal_at(k: int, point) -> np.ndarray | None:
            """The true outward normal of instance k + 1 at its surface point nearest `point`."""
            pts = surface[(scene.labels == k + 1) & valid]
            nearest = pts[np.argmin(np.linalg.norm(pts - point, axis=1))]
            return cylinder_normal(nearest, scene.poses[k], cam, r, h)

        truth["normal_at"] = normal_at
    for pk in compute_picks(clean_depth, scene.labels, cam.K, hidden):
        k = pk.instance - 1
        centroid[k] = pk.position
        if truth["normal_at"] is not None:
            got = truth["normal_at"](k, pk.position)
            if got is not None:
                normal[k] = got
    return truth


def match(pred_labels: np.ndarray, true_labels: np.ndarray, n_true: int) -> dict:
    """{predicted label: true label} by mask IoU, Hungarian, pairs with IoU >= MATCH_IOU."""
    from scipy.optimize import linear_sum_assignment

    n_pred = int(pred_labels.max())
    if n_pred == 0:
        return {}
    joint = np.bincount(pred_labels.astype(np.int64).ravel() * (n_true + 1)
                        + true_labels.astype(np.int64).ravel(),
                        minlength=(n_pred + 1) * (n_true + 1)).reshape(n_pred + 1, n_true + 1)
    inter = joint[1:, 1:].astype(float)
    union = joint[1:, :].sum(1)[:, None] + joint[:, 1:].sum(0)[None, :] - inter
    iou = inter / np.maximum(union, 1)
    rows, cols = linear_sum_assignment(-iou)
    return {int(r) + 1: int(c) + 1 for r, c in zip(rows, cols) if iou[r, c] >= MATCH_IOU}


def angle_deg(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0))))


def frame_errors(picks, pred_labels, truth: dict) -> dict:
    """Errors of one frame's picks (`picks.compute_picks` on `pred_labels`) against `truth`."""
    pairs = match(pred_labels, truth["labels"], len(truth["hidden"]))
    centroid, normal, normal_here = [], [], []
    for pk in picks:
        t = pairs.get(pk.instance)
        if t is None or truth["hidden"][t - 1] >= 0.5 or np.isnan(truth["centroid"][t - 1, 0]):
            continue
        centroid.append(float(np.linalg.norm(pk.position - truth["centroid"][t - 1])))
        if not np.isnan(truth["normal"][t - 1, 0]):
            normal.append(angle_deg(pk.normal, truth["normal"][t - 1]))
        here = truth["normal_at"](t - 1, pk.position) if truth.get("normal_at") else None
        if here is not None:
            normal_here.append(angle_deg(pk.normal, here))
    top = majority(pred_labels == picks[0].instance, truth["labels"]) if picks else None
    return {"centroid": centroid, "normal": normal, "normal_here": normal_here,
            "matched": len(pairs),
            "top_free": top is not None and truth["hidden"][top - 1] <= FREE_TRUE,
            "top_hidden": float(truth["hidden"][top - 1]) if top else float("nan")}


def majority(mask: np.ndarray, true_labels: np.ndarray) -> int | None:
    """The true instance that more than half of `mask`'s pixels belong to, else None."""
    counts = np.bincount(true_labels[mask].astype(np.int64), minlength=2)
    k = int(np.argmax(counts[1:])) + 1
    return k if counts[k] > mask.sum() / 2 else None


def _parse(argv) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="bench_picks", description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", type=int, default=50)
    ap.add_argument("--seed", type=int, default=3, help="scene k is scene_seed(seed, 'test', k)")
    ap.add_argument("--model", default="", help="model name or checkpoint ('' = cylinder)")
    ap.add_argument("--noise", default="none", help="sensor noise on the segmented frames: "
                    "none or realsense (the truth is always noise-free)")
    return ap.parse_args(argv)


def _run_scenes(args, model, noise, cfg) -> dict:
    """Each simulated scene segmented by `model` and picked, against its truth -> per figure,
    every value of every scene: the segmenter's picks' errors, the top picks, the compute
    times, and the true labels' picks' errors on the same depth ("oracle_...")."""
    from dataclasses import replace

    from inseggan_ros.runtime.picks import compute_picks, occluded_from_scores
    from inseggan_ros.runtime.preprocess import find_bin_roi
    from inseggan_ros.sim.dataset import scene_seed
    from inseggan_ros.sim.noise import apply_noise
    from inseggan_ros.sim.scene import BinSimulator

    r = {k: [] for k in ("centroid", "normal", "normal_here", "top_free", "top_hidden",
                         "matched", "ms", "oracle_c", "oracle_n")}
    roi = None
    with BinSimulator(cfg) as sim:
        for k in range(args.scenes):
            scene = sim.render(scene_seed(args.seed, "test", k))
            truth = scene_truth(sim, scene, scene.depth)
            depth = scene.depth
            if noise.enabled:
                depth = apply_noise(depth, noise, np.random.default_rng(k), fx=cfg.camera.fx)
            depth = np.round(depth * 1000) / 1000  # 16UC1 millimetres, as bin_replay sends
            roi = roi or find_bin_roi(depth)
            seg = model(depth, replace(model.prep_cfg, roi=roi, floor_depth=None),
                        reconstruction=False)
            t0 = time.perf_counter()
            picks = compute_picks(depth, seg.labels, cfg.camera.K,
                                  occluded_from_scores(seg.scores))
            r["ms"].append((time.perf_counter() - t0) * 1e3)
            e = frame_errors(picks, seg.labels, truth)
            o = frame_errors(compute_picks(depth, scene.labels, cfg.camera.K, truth["hidden"]),
                             scene.labels, truth)
            r["oracle_c"] += o["centroid"]
            r["oracle_n"] += o["normal"]
            for key in ("centroid", "normal", "normal_here"):
                r[key] += e[key]
            r["top_free"].append(e["top_free"])
            r["top_hidden"].append(e["top_hidden"])
            r["matched"].append(e["matched"])
    return r


def _print_report(args, cfg, model_path, r: dict) -> None:
    c, n = np.array(r["centroid"]) * 1e3, np.array(r["normal"])
    print(f"bench_picks: {args.scenes} simulated {cfg.object} bins ({cfg.instances} instances, "
          f"{cfg.camera.width}x{cfg.camera.height}, noise {args.noise}), model "
          f"{model_path}")
    print(f"  instances matched to the truth (IoU >= {MATCH_IOU}): {np.mean(r['matched']):.2f} "
          f"of {cfg.instances} a scene")
    print(f"  centroid error, matched instances more than half visible ({len(c)}): median "
          f"{np.median(c):.2f} mm, mean {c.mean():.2f} mm, p90 {np.percentile(c, 90):.2f} mm, "
          f"max {c.max():.2f} mm   [target < 5 mm]")
    print(f"  normal error, the same with a defined true normal ({len(n)}): median "
          f"{np.median(n):.2f} deg, mean {n.mean():.2f} deg, p90 {np.percentile(n, 90):.2f} deg, "
          f"max {n.max():.2f} deg   [target < 10 deg]")
    nh = np.array(r["normal_here"])
    print(f"  normal error at the point picked (against the true normal there, {len(nh)}): "
          f"median {np.median(nh):.2f} deg, mean {nh.mean():.2f} deg, p90 "
          f"{np.percentile(nh, 90):.2f} deg, max {nh.max():.2f} deg")
    oc, on = np.array(r["oracle_c"]) * 1e3, np.array(r["oracle_n"])
    print(f"  with the true labels on the same depth (the geometry's own error): centroid "
          f"median {np.median(oc):.2f} mm, max {oc.max():.2f} mm; normal median "
          f"{np.median(on):.2f} deg, max {on.max():.2f} deg")
    print(f"  top pick truly free (at most {FREE_TRUE:.0%} hidden): {np.mean(r['top_free']):.1%} "
          f"of {args.scenes} scenes   [target >= 95 %]; the top pick's true hidden share: "
          f"median {np.nanmedian(r['top_hidden']):.3f}, max {np.nanmax(r['top_hidden']):.3f}")
    print(f"  compute_picks: p50 {np.percentile(r['ms'], 50):.1f} ms a frame")


def main(argv=None) -> int:
    args = _parse(argv)
    import torch

    from inseggan_ros.core.paths import resolve_model
    from inseggan_ros.runtime.segment import Segmenter
    from inseggan_ros.sim.noise import get_noise
    from inseggan_ros.sim.scene import SceneConfig

    torch.set_num_threads(1)
    try:
        noise = get_noise(args.noise)
        model = Segmenter.from_checkpoint(resolve_model(args.model), device="cpu")
    except ValueError as e:
        print(f"bench_picks: error: {e}", file=sys.stderr)
        return 2
    cfg = SceneConfig(object="cylinder", instances=model.model_cfg.n_instances)
    r = _run_scenes(args, model, noise, cfg)
    _print_report(args, cfg, resolve_model(args.model), r)
    return 0


if __name__ == "__main__":
    sys.exit(main())
