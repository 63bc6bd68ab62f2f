"""The sensor noise measured on a recording's own frames (`sim.noise_fit`): simulated frames
made with the RealSense-like noise give back a noise of that kind and size, frames made
without noise give back none, so that the loop's piles need no preset named by the user."""
from __future__ import annotations

import numpy as np
import pytest

from inseggan_ros.io.bags import CameraInfo
from inseggan_ros.sim import user_camera
from inseggan_ros.sim.camera import get_camera
from inseggan_ros.sim.noise import NOISE_PRESETS, get_noise
from inseggan_ros.sim.scene import BinSimulator, SceneConfig


def _frames(preset: str, count: int = 8, seed: int = 7100):
    cam = get_camera("realsense_d435_tilted")
    cfg = SceneConfig(object="cylinder", instances=5, camera=cam, noise=get_noise(preset))
    with BinSimulator(cfg) as sim:
        frames = [sim.render(seed + i).depth for i in range(count)]
    return frames, CameraInfo.from_camera(cam)


@pytest.fixture(scope="module")
def realsense():
    frames, info = _frames("realsense")
    return user_camera.estimate_camera(frames, info)[1]


def test_frames_without_noise_measure_as_no_noise():
    frames, info = _frames("none", count=4)
    noise = user_camera.estimate_camera(frames, info)[1]["noise"]
    assert not noise.enabled, noise


def test_realsense_like_frames_give_back_their_noise(realsense):
    truth = NOISE_PRESETS["realsense"]
    got, measured = realsense["noise"], realsense["noise_measured"]
    z = measured["floor_depth_m"]
    sigma_true = truth.sigma_base + truth.sigma_per_m2 * z * z
    assert got.quantum == pytest.approx(truth.quantum)
    assert 0.6 * sigma_true < got.sigma_per_m2 * z * z < 1.5 * sigma_true
    assert truth.random_dropout / 2 < got.random_dropout < truth.random_dropout * 3
    assert truth.edge_dropout / 3 < got.edge_dropout < truth.edge_dropout * 1.5
    # the occlusion holes lie left of the parts: a stereo camera's, of about its baseline
    assert measured["left_right_holes"] > 2
    assert truth.stereo_baseline / 2 < got.stereo_baseline < truth.stereo_baseline * 1.5


def test_the_measured_noise_makes_frames_whose_holes_are_like_the_recordings(realsense):
    """Frames simulated with the measured noise lose about as many readings as the recording
    did, where noise-free frames of the same scenes lose none."""
    rec, info = _frames("realsense", count=4, seed=7300)
    cam = get_camera("realsense_d435_tilted")
    cfg = SceneConfig(object="cylinder", instances=5, camera=cam, noise=realsense["noise"])
    with BinSimulator(cfg) as sim:
        ours = [sim.render(7300 + i).depth for i in range(4)]
    lost_rec = np.mean([np.mean(f <= 0) for f in rec])
    lost_ours = np.mean([np.mean(f <= 0) for f in ours])
    assert lost_rec > 0.005
    assert 0.5 * lost_rec < lost_ours < 2 * lost_rec
