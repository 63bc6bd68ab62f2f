"""Picks: picks.py on synthetic planes and boxes (exact answers), and the segmenter's ~/picks
over real DDS between real processes (bin_replay -> segmenter -> a probe), against the
simulator's truth."""
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import installed_executable

from inseggan_ros.runtime import picks
from inseggan_ros.runtime.picks import PickConfig, compute_picks

pytestmark = pytest.mark.serial  # nodes over real DDS: run alone (setup.cfg)

HERE = Path(__file__).parent
K = np.array([[400.0, 0, 49.5], [0, 400.0, 39.5], [0, 0, 1]])  # a 100 x 80 image


def test_fronto_parallel_square_has_its_exact_centroid_normal_and_area():
    depth = np.zeros((80, 100))
    depth[30:50, 40:60] = 0.5  # 20 x 20 pixels, symmetric about the principal point
    labels = (depth > 0).astype(np.uint8)
    (p,) = compute_picks(depth, labels, K)
    np.testing.assert_allclose(p.position, [0, 0, 0.5], atol=1e-12)
    np.testing.assert_allclose(p.normal, [0, 0, -1], atol=1e-9)
    assert p.area == pytest.approx(400 * 0.5 ** 2 / 400.0 ** 2, rel=1e-9)
    assert p.free and p.rise == -np.inf and p.pixels == 400 and p.instance == 1


def _tilted_plane(normal, h, shape=(80, 100)):
    """Depth of the plane {P: normal . P = -h} (normal toward the camera) over the image."""
    x, y = picks.rays(K, shape)
    return -h / (normal[0] * x + normal[1] * y + normal[2])


def test_tilted_plane_has_its_exact_normal_and_area_and_a_centroid_on_it():
    n = np.array([0.3, -0.2, -1.0])
    n /= np.linalg.norm(n)
    depth = _tilted_plane(n, 0.4)
    labels = np.zeros(depth.shape, np.uint8)
    labels[20:60, 30:70] = 1
    (p,) = compute_picks(depth, labels, K, cfg=PickConfig(normal_radius=0.05))
    np.testing.assert_allclose(p.normal, n, atol=1e-9)
    assert p.normal @ p.position < 0, "toward the camera"
    assert n @ p.position == pytest.approx(-0.4, abs=1e-12), "the centroid lies on the plane"
    # the area of the plane patch the 40 x 40 pixels cover: the back-projected corners of the
    # region (pixel edges at +-0.5) span a planar quadrilateral
    corners = np.array([[29.5, 19.5], [69.5, 19.5], [69.5, 59.5], [29.5, 59.5]])
    x, y = (corners[:, 0] - K[0, 2]) / K[0, 0], (corners[:, 1] - K[1, 2]) / K[1, 1]
    z = -0.4 / (n[0] * x + n[1] * y + n[2])
    q = np.stack([x * z, y * z, z], 1)
    quad = 0.5 * np.linalg.norm(np.cross(q[2] - q[0], q[3] - q[1]))
    assert p.area == pytest.approx(quad, rel=1e-3)
    # and the centroid is where the camera sees the middle of the patch, to a pixel
    u = K[0, 0] * p.position[0] / p.position[2] + K[0, 2]
    v = K[1, 1] * p.position[1] / p.position[2] + K[1, 2]
    assert abs(u - 49.5) < 1 and abs(v - 39.5) < 1


def test_box_on_box_the_upper_one_is_picked_first_and_the_lower_is_under_it():
    depth = np.full((80, 100), 0.5)  # floor
    labels = np.zeros(depth.shape, np.uint8)
    depth[20:60, 10:60], labels[20:60, 10:60] = 0.47, 1  # a low box ...
    depth[30:50, 45:80], labels[30:50, 45:80] = 0.45, 2  # ... and one lying across its edge
    depth[10:20, 85:95], labels[10:20, 85:95] = 0.46, 3  # alone, lower than box 2
    got = compute_picks(depth, labels, K, occluded=[0.3, 0.0, 0.0])
    assert [p.instance for p in got] == [2, 3, 1]  # free ones, top-most first; then the rest
    assert [p.free for p in got] == [True, True, False]
    assert got[2].rise == pytest.approx(0.02) and got[2].occluded == pytest.approx(0.3)
    box1 = got[2]
    visible = (labels == 1).sum()
    assert box1.area == pytest.approx(visible * 0.47 ** 2 / 400.0 ** 2, rel=1e-9)
    np.testing.assert_allclose(box1.normal, [0, 0, -1], atol=1e-9)
    assert box1.top_depth == pytest.approx(0.47)


def test_hidden_share_of_a_render_is_what_other_labels_cover():
    renders = np.full((3, 4, 4), -1.0)
    renders[0, :2, :] = 0.5  # 8 pixels drawn ...
    renders[1, 1:3, :] = 0.5  # 8 pixels drawn, the upper one
    labels = np.zeros((4, 4), np.uint8)
    labels[0, :] = 1  # ... 4 of them won by instance 1
    labels[1:3, :] = 2  # and 4 lost to instance 2
    got = picks.hidden_from_renders(renders, labels, tau=0.0)
    np.testing.assert_allclose(got, [0.5, 0.0, 0.0])  # instance 3: not drawn
    labels[3, :] = 3  # a piece split off another instance: it holds pixels, its score is 0
    got = picks.hidden_from_renders(renders, labels, tau=0.0, scores=[0.5, 1.0, 0.0])
    np.testing.assert_allclose(got, [0.5, 0.0, 1.0])
    np.testing.assert_allclose(picks.occluded_from_scores([1.2, 0.25, 0.0]), [0, 0.75, 1])


def test_orientation_has_the_normal_as_its_z_axis():
    from scipy.spatial.transform import Rotation

    for n in ([0, 0, -1], [0.6, 0, -0.8], [-0.95, 0.1, -0.3], [1, 0, 0]):
        n = np.array(n, float) / np.linalg.norm(n)
        p = picks.Pick(1, np.zeros(3), n, 0.0, 0.0, -np.inf, True, 0.0, 10)
        R = Rotation.from_quat(p.orientation()).as_matrix()
        np.testing.assert_allclose(R[:, 2], n, atol=1e-12)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)


def test_quaternion_is_scipys():
    """`Pick.orientation`'s quaternion, written out, is scipy's Rotation.from_matrix(R)
    .as_quat() on every branch (largest diagonal entry or trace), with its sign."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    normals = [rng.normal(size=3) for _ in range(2000)] + [np.array([0, 0, -1.0]),
                                                           np.array([1.0, 0, 0])]
    for n in normals:
        R = picks.frame_from_normal(n / np.linalg.norm(n))
        np.testing.assert_allclose(picks.quaternion_from_matrix(R),
                                   Rotation.from_matrix(R).as_quat(), atol=1e-15)
    for R in Rotation.random(500, random_state=6).as_matrix():
        np.testing.assert_allclose(picks.quaternion_from_matrix(R),
                                   Rotation.from_matrix(R).as_quat(), atol=1e-14)


def test_surface_is_the_points_arrays_centroid_and_normal():
    """`_surface` on contiguous columns: the centroid, the near points and the normal of the
    (N, 3) array's own reductions, up to the order of the sums."""
    rng = np.random.default_rng(7)
    for _ in range(50):
        zs = 0.5 + 0.01 * rng.random(3000)
        pts = np.stack([rng.random(3000) * 0.05 * zs, rng.random(3000) * 0.05 * zs, zs], 1)
        footprint = zs ** 2
        centroid = (pts * footprint[:, None]).sum(0) / footprint.sum()
        dist = np.linalg.norm(pts - centroid, axis=1)
        near = dist <= dist.min() + 0.004
        got_centroid, got_normal = picks._surface(pts, zs, 0.004)
        np.testing.assert_allclose(got_centroid, centroid, rtol=1e-13)
        np.testing.assert_allclose(got_normal, picks.plane_normal(pts[near], footprint[near]),
                                   atol=1e-9)


def test_bad_input_is_named():
    depth = np.ones((80, 100))
    with pytest.raises(ValueError, match="depth .* and labels .* must be the same"):
        compute_picks(depth, np.ones((80, 99), np.uint8), K)
    with pytest.raises(ValueError, match="K .* invalid; valid: fx > 0"):
        compute_picks(depth, np.ones((80, 100), np.uint8), np.zeros(9))
    with pytest.raises(ValueError, match="has 4 values"):
        compute_picks(depth, np.ones((80, 100), np.uint8), np.zeros(4))
    with pytest.raises(ValueError, match="normal_radius"):
        PickConfig(normal_radius=0)
    small = np.zeros((80, 100), np.uint8)
    small[:3, :3] = 1  # 9 pixels: below min_pixels, no pick
    assert compute_picks(depth, small, K) == []


# ---------------------------------------------------------------------- over DDS
def _start(name, ns, *args, env=None):
    exe = [str(installed_executable(name)), "--ros-args", "-r", f"__ns:={ns}", *args]
    return subprocess.Popen(exe, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)


def _probe(tmp, ns, count, timeout, wait_for, *info):
    out = tmp / "picks.npz"
    proc = subprocess.Popen([sys.executable, str(HERE / "pick_probe.py"), str(out), ns,
                             str(count), str(timeout), wait_for, *map(str, info)],
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "probe ready"
    return proc, out


def _run(tmp, ns, count, seg_args=(), info=(), timeout=150, wait_for="picks"):
    """Segmenter + probe + bin_replay (simulated cylinders, seed 0, 2 Hz), all in `ns` with
    their default topics -> (what the probe saved, the segmenter's stderr)."""
    from test_bin_replay import stop

    seg = _start("segmenter", ns, *seg_args)
    probe, out = _probe(tmp, ns, count, timeout, wait_for, *info)
    replay = _start("bin_replay", ns, "-p", "rate:=2.0", "-p", "seed:=0")
    try:
        rc = probe.wait(timeout=timeout + 30)
    finally:
        stop(replay)
        seg_rc = stop(seg)
    err = seg.stderr.read()
    assert seg_rc == 0 and "Traceback" not in err, err
    got = dict(np.load(out, allow_pickle=True))
    got["diagnostics"] = got["diagnostics"].item()
    assert rc == 0, f"probe got {len(got['stamp'])} frames\n{err}"
    return got, err


def test_picks_over_dds_match_the_simulator(tmp):
    """bin_replay and the segmenter started side by side with no remap are connected (the
    labels and picks come back), and each frame's PoseArray is what picks.py computes from the
    depth and labels that went over DDS, close to the simulator's truth."""
    from tools.bench_picks import frame_errors, scene_truth
    from inseggan_ros.core.image_codec import depth_to_metres, metres_to_depth
    from inseggan_ros.sim.dataset import scene_seed
    from inseggan_ros.sim.scene import BinSimulator, SceneConfig

    # the bin region fixed: found per stream from its first frames, it depends on which frames
    # arrive first (a slow start misses some), and a region found on scene 4 alone cuts the
    # top of the bin and costs that frame its free pick; the finder has tests of its own
    got, err = _run(tmp, "/picks_e2e", 6, seg_args=("-p", "roi:=[58,57,167,166]"))
    assert "Fast DDS profile for large frames" in err  # no profile set: the node set its own
    cfg = SceneConfig()
    centroid, normal, top_free = [], [], []
    with BinSimulator(cfg) as sim:
        scenes = [sim.render(scene_seed(0, "test", k)) for k in range(40)]
        for i in range(len(got["stamp"])):
            raw, labels, poses = got["depth"][i], got["labels"][i], got["poses"][i]
            assert got["picks_frame_id"][i] == got["depth_frame_id"][i] == \
                "camera_depth_optical_frame"  # the input's header (the stamp is the key)
            depth = depth_to_metres(raw, "16UC1")
            want = compute_picks(depth, labels, cfg.camera.K)
            assert len(poses) == len(want) >= 1
            for p, w in zip(poses, want):  # same order, same numbers
                np.testing.assert_allclose(p[:3], w.position, atol=1e-9)
                np.testing.assert_allclose(p[3:], w.orientation(), atol=1e-9)
            markers = got["markers"][i]
            assert markers[0][1] == 3  # DELETEALL first, then an arrow and a text per pick
            assert len(markers) == 1 + 2 * len(want)
            assert {m[3] for m in markers} == {"camera_depth_optical_frame"}
            k = [j for j, s in enumerate(scenes)
                 if np.array_equal(raw, metres_to_depth(s.depth, "16UC1"))]
            assert len(k) == 1, "the frame is one of the simulated scenes"
            sim.render(scene_seed(0, "test", k[0]))  # the simulator holds this scene again
            truth = scene_truth(sim, scenes[k[0]], scenes[k[0]].depth)
            e = frame_errors(want, labels, truth)
            centroid += e["centroid"]
            normal += e["normal"]
            top_free.append(e["top_free"])
    # bench_picks --seed 0 --scenes 40 (this region): the top pick is free in all but scene 5
    print(f"picks: centroid error median {np.median(centroid) * 1000:.1f} mm of "
          f"{len(centroid)}, normal {np.median(normal):.1f} deg; top free {top_free}")
    assert len(centroid) >= 10
    assert np.median(centroid) < 0.003, centroid
    assert np.median(normal) < 8.0, normal
    assert sum(top_free) >= len(top_free) - 1, top_free
    d = got["diagnostics"]["segmenter: picks"]
    assert d["_level"] == "0" and int(d["picks_published"]) >= 6 and d["last_picks"]


@pytest.mark.parametrize("remap, info, message", [
    ("no_info", (), "no CameraInfo received on /picks_{}/no_info: no picks"),
    ("wrong_info", ("/picks_{}/wrong_info", 100, 80),
     "CameraInfo on /picks_{}/wrong_info is 100x80 but the depth is 224x224: no picks"),
])
def test_without_a_matching_camera_info_labels_go_on_and_diagnostics_say_why(
        tmp, remap, info, message):
    ns = f"/picks_{remap}"
    info = tuple(x.format(remap) if isinstance(x, str) else x for x in info)
    message = message.format(remap)
    got, err = _run(tmp, ns, 3, seg_args=("-r", f"camera/depth/camera_info:={remap}"),
                    info=info, timeout=90, wait_for="labels")
    assert len(got["labels"]) == 3 and int(got["picks_total"]) == 0
    d = got["diagnostics"]["segmenter: picks"]
    assert d["_level"] == "1" and d["_message"] == message, d
    assert d["camera_info_topic"] == f"{ns}/{remap}"
    assert got["diagnostics"]["segmenter: instance segmentation"]["frames_skipped"] == "0"
    assert message in err  # the warning, throttled (every 5 s) ...
    received = int(got["diagnostics"]["segmenter: instance segmentation"]["frames_received"])
    assert err.count(message) < received, "... not one a frame"


def test_camera_info_is_taken_beside_a_remapped_depth_topic():
    """And a remap of `depth` (the name the segmenter subscribed to before) is pointed out."""
    from test_bin_replay import stop

    seg = _start("segmenter", "/picks_beside", "-r",
                 "camera/depth/image_rect_raw:=/cam2/depth/image_rect_raw", "-r", "depth:=/old")
    try:
        deadline, lines = time.monotonic() + 90, [""]
        while "listening on" not in lines[-1] and time.monotonic() < deadline:
            lines.append(seg.stderr.readline())
            if not lines[-1] and seg.poll() is not None:
                break
    finally:
        stop(seg)
    assert "listening on /cam2/depth/image_rect_raw (camera info: /cam2/depth/camera_info)" \
        in lines[-1], lines
    assert any("the remap of 'depth' has no effect: the depth topic is "
               "camera/depth/image_rect_raw" in line for line in lines), lines


def test_bench_truth_tells_a_moved_pick_point_from_a_wrong_plane():
    """bench_picks' two normal figures: against the true normal at the true centroid, and at
    the point the pick names. Every instance cut to 60 % of its width (a segmentation that
    split it along its length) moves its centroid across a curved side: the first error grows,
    the second, the fitted plane's own, stays that of the true labels."""
    from tools.bench_picks import frame_errors, scene_truth
    from inseggan_ros.sim.dataset import scene_seed
    from inseggan_ros.sim.scene import BinSimulator, SceneConfig

    cfg = SceneConfig()
    with BinSimulator(cfg) as sim:
        scene = sim.render(scene_seed(0, "test", 0))
        truth = scene_truth(sim, scene, scene.depth)
    depth, K_cam = scene.depth, cfg.camera.K
    exact = frame_errors(compute_picks(depth, scene.labels, K_cam), scene.labels, truth)
    assert len(exact["normal"]) >= 2
    np.testing.assert_allclose(exact["normal_here"], exact["normal"])  # the same points
    cut = scene.labels.copy()
    for k in range(1, int(cut.max()) + 1):
        rows, cols = np.nonzero(cut == k)
        if len(rows) < 20:
            continue
        uv = np.stack([cols, rows], 1).astype(float)
        uv -= uv.mean(0)
        minor = np.linalg.eigh(uv.T @ uv)[1][:, 0]  # across the instance
        side = uv @ minor
        drop = side < np.percentile(side, 40)
        cut[rows[drop], cols[drop]] = 0
    moved = frame_errors(compute_picks(depth, cut, K_cam), cut, truth)
    print(f"true labels: normal errors {np.round(exact['normal'], 1)}; cut: at the true "
          f"centroid {np.round(moved['normal'], 1)}, at the point picked "
          f"{np.round(moved['normal_here'], 1)}")
    assert len(moved["normal_here"]) >= 2
    assert max(moved["normal"]) > 2 * max(exact["normal"]) + 5
    assert max(moved["normal_here"]) < max(exact["normal"]) + 5
