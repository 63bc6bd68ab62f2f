"""The simulator: object library, camera geometry, determinism, ground truth, noise."""
import numpy as np
import pytest

from inseggan_ros.sim.camera import CameraConfig, get_camera
from inseggan_ros.sim.noise import NoiseConfig, apply_noise, get_noise, occlusion_holes
from inseggan_ros.sim.objects import OBJECTS, get_object
from inseggan_ros.sim.scene import BinSimulator, SceneConfig


def test_library_has_the_industrial_parts():
    for name in ("cylinder", "cone", "hex_nut", "bolt", "wooden_block"):
        assert name in OBJECTS
    assert len(OBJECTS) >= 7
    for spec in OBJECTS.values():
        ext = spec.extent
        assert 0.004 < ext.min() and ext.max() < 0.08, f"{spec.name} is not a few cm: {ext}"
        t = spec.mesh.triangles
        assert t.min() == 0 and t.max() < len(spec.mesh.vertices)
        assert spec.mass > 0


def test_unknown_object_lists_valid_names():
    with pytest.raises(ValueError, match="valid: cylinder, cone"):
        get_object("teapot")


def test_projection_matches_pinhole_model():
    # An off-centre principal point: a cone's apex region must land where u = fx X/Z + cx says.
    cam = CameraConfig(width=160, height=120, fx=300, fy=280, cx=70.0, cy=52.0, mount_height=0.5)
    with BinSimulator(SceneConfig(object="wooden_block", instances=1, camera=cam)) as sim:
        scene = sim.render(3)
    floor = scene.depth[scene.labels == 0]
    # bin floor visible in most of the image is at the mount height (z-buffer -> metres)
    assert np.median(floor) == pytest.approx(0.5, abs=1e-3)
    ys, xs = np.nonzero(scene.labels == 1)
    u, v = cam.project(scene.poses[:, :3])[0]
    assert abs(xs.mean() - u) < 3 and abs(ys.mean() - v) < 3
    # the depth at the object's centre is the camera height minus the object's height there
    assert scene.depth[int(round(v)), int(round(u))] < 0.5 - 0.005


def test_same_seed_same_scene_whatever_came_before():
    cfg = SceneConfig(object="bolt")
    with BinSimulator(cfg) as a, BinSimulator(cfg) as b:
        a.render(1)
        a.render(2)
        x, y = a.render(7), b.render(7)
    assert np.array_equal(x.depth, y.depth) and np.array_equal(x.labels, y.labels)
    with BinSimulator(cfg) as c:
        assert not np.array_equal(c.render(8).labels, x.labels)


@pytest.mark.parametrize("name", list(OBJECTS))
def test_every_object_makes_a_plausible_bin(name):
    cfg = SceneConfig(object=name, instances=5)
    with BinSimulator(cfg) as sim:
        scene = sim.render(0)
    cam = cfg.camera
    assert scene.depth.shape == (cam.height, cam.width) and scene.depth.dtype == np.float32
    assert scene.labels.dtype == np.uint8
    visible = [k for k in range(1, 6) if (scene.labels == k).sum() > 20]
    assert len(visible) >= 4, f"{name}: only {len(visible)} of 5 instances visible"
    assert set(np.unique(scene.labels)) <= set(range(6))
    # objects lie on the bin floor: above it (nearer the camera), within an object's size
    obj = scene.depth[scene.labels > 0]
    assert (obj < cam.mount_height - 0.001).mean() > 0.95
    assert obj.min() > cam.mount_height - 0.1
    # every object is inside the bin
    half = np.asarray(cfg.bin.inner_size) / 2
    assert (np.abs(scene.poses[:, :2]) < half).all()


def test_hex_nut_has_a_real_hole():
    # a nut lying flat shows the floor (or what is below) through its hole
    cfg = SceneConfig(object="hex_nut", instances=1)
    with BinSimulator(cfg) as sim:
        for seed in range(20):
            s = sim.render(seed)
            q = s.poses[0, 3:]
            tilt = 1 - 2 * (q[0] ** 2 + q[1] ** 2)  # z of the nut's axis in the world
            if abs(tilt) > 0.99:
                u, v = cfg.camera.project(s.poses[:, :3])[0]
                assert s.labels[int(round(v)), int(round(u))] == 0
                return
    pytest.skip("no flat-lying nut in 20 drops")


def test_realsense_preset_and_noise_model():
    cam = get_camera("realsense_d435")
    assert (cam.width, cam.height) == (848, 480)
    cfg = SceneConfig(object="wooden_block", instances=4, camera=cam, noise=get_noise("realsense"))
    with BinSimulator(cfg) as sim:
        s = sim.render(0)
    assert s.depth.shape == (480, 848)
    valid = s.depth > 0
    assert 0.001 < (~valid).mean() < 0.2, "some pixels are lost, most are not"
    np.testing.assert_allclose(s.depth[valid] * 1000, np.round(s.depth[valid] * 1000), atol=1e-3)


def test_noise_statistics():
    rng = np.random.default_rng(0)
    clean = np.full((200, 200), 0.5, np.float32)
    noisy = apply_noise(clean, NoiseConfig(sigma_base=0.002), rng)
    assert np.std(noisy - clean) == pytest.approx(0.002, rel=0.05)
    edge = clean.copy()
    edge[:, 100:] = 0.45
    lost = apply_noise(edge, NoiseConfig(edge_dropout=1.0), rng) == 0
    assert lost[:, 98:102].all() and not lost[:, :90].any()
    with pytest.raises(ValueError, match="probability"):
        NoiseConfig(random_dropout=2.0)


def test_stereo_occlusion_holes_lie_beside_nearer_surfaces():
    # a floor at 0.5 m and a box 5 cm nearer on columns 100..139; imagers 50 mm apart, fx 400
    depth = np.full((40, 200), 0.5, np.float32)
    depth[:, 100:140] = 0.45
    hidden = occlusion_holes(depth, 0.05 * 400)
    # the band the second imager cannot see: left of the box, baseline * fx * (1/0.45 - 1/0.5)
    # = 4.4 pixels wide (less the half-pixel margin), nothing on the box or right of it
    width = 0.05 * 400 * (1 / 0.45 - 1 / 0.5)
    cols = np.flatnonzero(hidden.any(0))
    assert hidden[:, cols].all() and cols.max() == 99 and width - 1.5 <= len(cols) <= width
    assert not hidden[:, 100:].any()
    # the RealSense preset makes them (as 0), and needs the focal length to
    noisy = apply_noise(depth, get_noise("realsense"), np.random.default_rng(0), fx=400.0)
    assert (noisy[:, cols] == 0).all()
    with pytest.raises(ValueError, match="stereo_baseline .* focal length fx"):
        apply_noise(depth, get_noise("realsense"), np.random.default_rng(0))
    assert NoiseConfig(stereo_baseline=0.05).enabled


def test_simulated_holes_lie_on_the_far_side_of_depth_edges():
    cfg = SceneConfig(object="cylinder", camera=get_camera("realsense_d435"),
                      noise=get_noise("realsense"))
    with BinSimulator(cfg) as sim:
        s = sim.render(2)
    clean_cfg = SceneConfig(object="cylinder", camera=get_camera("realsense_d435"))
    with BinSimulator(clean_cfg) as sim:
        clean = sim.render(2).depth
    hidden = occlusion_holes(clean, cfg.noise.stereo_baseline * cfg.camera.fx)
    assert hidden.mean() > 0.005 and (s.depth[hidden] == 0).all()
    # each hidden pixel is farther than a pixel a few columns to its right
    rows, cols = np.nonzero(hidden)
    nearer = np.stack([clean[rows, np.minimum(cols + k, clean.shape[1] - 1)]
                       for k in range(1, 21)], 1).min(1)
    assert (nearer < clean[rows, cols] - 0.004).mean() > 0.99


def test_bad_configs_are_rejected_clearly():
    with pytest.raises(ValueError, match=r"in 0..20 \(0 = an empty bin\), got 21"):
        SceneConfig(instances=21)
    with pytest.raises(ValueError, match="instances must be in 0..20"):
        SceneConfig(instances=-1)
    with pytest.raises(ValueError, match=r"min_instances must be in 0..instances \(3\)"):
        SceneConfig(instances=3, min_instances=4)
    with pytest.raises(ValueError, match="min_instances must be in 0..instances"):
        SceneConfig(instances=3, min_instances=-1)
    with pytest.raises(ValueError, match="unknown camera preset 'kinect'; valid: default"):
        get_camera("kinect")


def test_parts_that_do_not_fit_the_bin_are_named_not_crashed_on():
    """Twenty blocks dropped anywhere over a 31 mm bin with 5 mm walls: every pile loses a
    part, and the scene is given up with an error that names the part's size and the bin's (a
    ValueError, so the command line prints one line; `inseggan loop` meets it when a learned
    shape is still far too large)."""
    from inseggan_ros.sim.scene import BinConfig, PileError

    cfg = SceneConfig(object="wooden_block", instances=20, drop_spread=1.0,
                      bin=BinConfig(inner_size=(0.031, 0.031), wall_height=0.005))
    want = (r"fell out of the 31 x 31 mm bin in 5 drops, in each of 4 piles started afresh; "
            "valid: a part that fits")
    with BinSimulator(cfg) as sim, pytest.raises(PileError, match=want):
        sim.render(0)


def test_a_pile_that_loses_a_part_is_piled_again_not_given_up(monkeypatch):
    """A part that fits the bin still bounces out now and then (a large learned part: one scene
    in 150 of the tilted recording's young rod); the scene is then piled again from a seed
    derived from its own, so that one unlucky scene does not stop a data set. Here the bin
    check is made to fail every drop of the first pile (as a part that bounced out five
    times), then pass."""
    from inseggan_ros.sim.scene import DROPS

    cfg = SceneConfig(object="cylinder", instances=3)
    with BinSimulator(cfg) as sim:
        first = sim.render(5)
        assert sim.last_piles == 1
        real, calls = BinSimulator._inside_bin, []

        def unlucky(self, body):
            calls.append(body)
            return len(calls) > DROPS and real(self, body)

        monkeypatch.setattr(BinSimulator, "_inside_bin", unlucky)
        again = sim.render(5)
        assert sim.last_piles == 2 and len(calls) >= DROPS + cfg.instances
        assert set(np.unique(again.labels)) == {0, 1, 2, 3}  # every part in the bin and seen
        assert not np.array_equal(again.depth, first.depth)  # another pile, not the seed's
        monkeypatch.undo()
        np.testing.assert_array_equal(sim.render(5).depth, first.depth)  # deterministic
