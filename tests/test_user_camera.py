"""The camera of the user: the simulator's camera and bin estimated from a bag of depth frames
with its CameraInfo (sim.user_camera, `inseggan simulate --camera-from`).

Frames come from the real simulator (RealSense-like noise, 16UC1 millimetres) through a real
MCAP bag. Measured over 3-8 frames of six views (tilts 0-20 degrees, bins of 9 x 9 and
15 x 12 cm, 848 x 480 and 424 x 240): the tilt within 0.12 degree, the roll within 0.9 degree
at 3 degrees of tilt (0.55 at 848 x 480) and 0.3 at 10 or more, the mount height within
0.4 mm, the bin offset within 0.006 and the bin inner size within 4.5 %, with 6 frames or more
(with 3, one view had a side 20 % short: objects that stayed beside a wall). The tolerances
below leave margin over those figures.
"""
import json
import math
from dataclasses import replace

import numpy as np
import pytest

from conftest import refused, run_cli
from inseggan_ros.io import bags
from inseggan_ros.runtime.preprocess import roi_from_camera
from inseggan_ros.sim.camera import CameraConfig, get_camera
from inseggan_ros.sim.noise import get_noise
from inseggan_ros.sim.scene import BinConfig, BinSimulator, SceneConfig
from inseggan_ros.sim.user_camera import estimate_camera, pose_from_plane

FRAMES = 6
# name: (camera, bin); the preset at its own 848 x 480 (the roll of a 3-degree tilt wants the
# pixels), the 10-degree view at half that size with a larger bin off-centre
VIEWS = {
    "d435_tilted": (get_camera("realsense_d435_tilted"), BinConfig()),
    "tilt10": (replace(get_camera("realsense_d435"), tilt=10.0, roll=-4.0,
                       bin_offset=(0.12, -0.1)).resized(424, 240),
               BinConfig(inner_size=(0.15, 0.12))),
}


def _write_bag(path, frames, camera, with_info=True) -> None:
    info = bags.CameraInfo.from_camera(camera) if with_info else None
    bags.write_frames(path, [(1_700_000_000_000_000_000 + k * 100_000_000, d, None, info)
                             for k, d in enumerate(frames)])


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """{view: (camera, bin, bag path)}: FRAMES simulated frames of each view in a bag."""
    root = tmp_path_factory.mktemp("user_camera")
    out = {}
    for name, (camera, bin_cfg) in VIEWS.items():
        cfg = SceneConfig(object="cylinder", camera=camera, bin=bin_cfg,
                          noise=get_noise("realsense"))
        with BinSimulator(cfg) as sim:
            frames = [sim.render(seed).depth for seed in range(FRAMES)]
        _write_bag(root / name, frames, camera)
        out[name] = camera, bin_cfg, root / name
    return out


def _estimate(bag):
    frames = list(bags.read_frames(bag))
    return estimate_camera([f.metres() for f in frames], frames[-1].camera_info)


@pytest.mark.parametrize("view", list(VIEWS))
def test_camera_and_bin_come_back_from_a_bag(recorded, view):
    true, bin_cfg, bag = recorded[view]
    cam, est = _estimate(bag)
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == \
        (true.width, true.height, true.fx, true.fy, true.cx, true.cy)
    assert est["frames"] == FRAMES and all(est["walls_found"])
    assert abs(cam.tilt - true.tilt) < 0.5, cam.tilt
    if true.tilt >= 3:
        assert abs((cam.roll - true.roll + 180) % 360 - 180) < 1.5, cam.roll
    assert abs(cam.mount_height - true.mount_height) < 0.005, cam.mount_height
    assert np.abs(np.subtract(cam.bin_offset, true.bin_offset)).max() < 0.02, cam.bin_offset
    size = np.asarray(est["bin_inner_size"])
    assert np.abs(size / bin_cfg.inner_size - 1).max() < 0.10, size
    assert abs(est["wall_height"] - bin_cfg.wall_height) < 0.005, est["wall_height"]
    # the simulator, given the estimate, puts the bin floor where the frames show it
    x0, y0, x1, y1 = roi_from_camera(true, bin_cfg)
    e0, f0, e1, f1 = roi_from_camera(cam, replace(bin_cfg, inner_size=tuple(size)))
    inter = max(0, min(x1, e1) - max(x0, e0)) * max(0, min(y1, f1) - max(y0, f0))
    union = (x1 - x0) * (y1 - y0) + (e1 - e0) * (f1 - f0) - inter
    assert inter / union > 0.85, (inter / union, (x0, y0, x1, y1), (e0, f0, e1, f1))


def test_pose_from_plane_inverts_the_floor_plane_exactly():
    rng = np.random.default_rng(3)
    for _ in range(20):
        cam = CameraConfig(width=640, height=400, fx=rng.uniform(200, 900),
                           fy=rng.uniform(200, 900), cx=rng.uniform(250, 390),
                           cy=rng.uniform(150, 250), mount_height=rng.uniform(0.2, 1.5),
                           far=3.0, tilt=rng.uniform(1, 45), roll=rng.uniform(-180, 180),
                           bin_offset=tuple(rng.uniform(-0.1, 0.1, 2)))
        h, tilt, roll = pose_from_plane(cam.floor_plane(), cam.fx, cam.fy, cam.cx, cam.cy)
        assert h == pytest.approx(cam.mount_height, rel=1e-9)
        assert tilt == pytest.approx(cam.tilt, abs=1e-7)
        assert abs((roll - cam.roll + 180) % 360 - 180) < 1e-7
        # and back: the same floor
        back = replace(cam, mount_height=h, tilt=tilt, roll=roll)
        assert np.allclose(back.floor_plane(), cam.floor_plane(), rtol=1e-9, atol=1e-15)
    # a negative tilt is the same floor as the positive one turned half a turn
    h, tilt, roll = pose_from_plane(CameraConfig(tilt=-10.0, roll=30.0).floor_plane(),
                                    420.0, 420.0, 111.5, 111.5)
    assert tilt == pytest.approx(10.0) and roll == pytest.approx(-150.0)
    # looking straight down: the roll is not in the floor, and reads 0
    assert pose_from_plane(CameraConfig(roll=40.0).floor_plane(), 420.0, 420.0, 111.5,
                           111.5)[1:] == (0.0, 0.0)


def test_bad_input_is_refused_naming_what_is_valid(recorded):
    camera, _, bag = recorded["tilt10"]
    frames = [f.metres() for f in bags.read_frames(bag)]
    info = bags.CameraInfo.from_camera(camera)
    with pytest.raises(ValueError, match="no depth frames.*valid"):
        estimate_camera([], info)
    with pytest.raises(ValueError, match="camera info says 424x240.*valid"):
        estimate_camera([f[:, :200] for f in frames], info)
    with pytest.raises(ValueError, match="no bin floor found.*valid"):
        estimate_camera([np.full((240, 424), 0.3, np.float32)], info)
    # a camera info that does not belong to the frames (8 times the focal length): the floor
    # would be tilted far more than a camera looking into a bin is
    wrong = bags.CameraInfo(424, 240, camera.K * np.array([[8, 1, 1], [1, 8, 1], [1, 1, 1]]))
    with pytest.raises(ValueError, match="tilted .* degrees.*valid: at most 45"):
        estimate_camera(frames, wrong)


def test_simulate_camera_from_a_bag(recorded, tmp):
    _, bin_cfg, bag = recorded["tilt10"]
    cam, est = _estimate(bag)
    out = tmp / "data"
    proc = run_cli("simulate", "--camera-from", bag, "--count", 4, "--workers", 1, "--quiet",
                   "--out", out, check=True)
    assert f"tilt {cam.tilt:.2f} deg" in proc.stdout and "bin inner size" in proc.stdout
    scene = json.loads((out / "meta.json").read_text())["scene"]
    recorded_cam = CameraConfig(**scene["camera"])
    for key, value in cam.to_dict().items():
        assert getattr(recorded_cam, key) == pytest.approx(value), key
    assert scene["bin"]["inner_size"] == pytest.approx(list(est["bin_inner_size"]))
    assert scene["bin"]["wall_height"] == BinConfig().wall_height  # the rest as it was
    assert math.isclose(scene["camera"]["tilt"], 10.0, abs_tol=0.5)
    # --camera and --camera-from exclude each other
    proc = refused("simulate", "--camera-from", bag, "--camera", "default", "--count", 4,
                   "--out", tmp / "other")
    assert proc.returncode == 2 and "mutually exclusive" in proc.stderr


def test_bag_without_camera_info_is_refused(recorded, tmp):
    camera, _, bag = recorded["tilt10"]
    frames = [f.metres() for f in bags.read_frames(bag)]
    _write_bag(tmp / "no_info", frames, camera, with_info=False)
    proc = refused("simulate", "--camera-from", tmp / "no_info", "--count", 4,
                   "--out", tmp / "data")
    assert proc.returncode == 2, proc.stderr
    assert "no sensor_msgs/CameraInfo" in proc.stderr
    assert "valid: a bag with a sensor_msgs/CameraInfo beside the depth topic, or --camera " \
        "PRESET" in proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp / "data").exists()
