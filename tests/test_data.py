"""data: simulated shards and bags -> the same model input; the torch data set and augmentation."""
import numpy as np
import pytest
import torch
from conftest import BAGS

from inseggan_ros.data.datasets import (
    DepthTensorDataset, load_bag, load_sim_split, rotate, sim_preprocess_config)
from inseggan_ros.runtime.preprocess import PreprocessConfig, roi_from_camera
from inseggan_ros.sim.camera import get_camera
from inseggan_ros.sim.dataset import DatasetSpec, generate, load_meta
from inseggan_ros.sim.scene import SceneConfig


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """Seed 0, default scene: its test split holds the scenes of the shipped bag cylinder_sim."""
    out = tmp_path_factory.mktemp("data") / "cylinder"
    generate(DatasetSpec(SceneConfig(), {"train": 3, "test": 4}, seed=0, shard_size=3), out,
             workers=1, progress=False)
    return out


def check_split(d, n, size=64, labels=True):
    assert d["x"].shape == (n, 1, size, size) and d["x"].dtype == np.float32
    assert d["fg"].shape == (n, size, size) and d["fg"].dtype == bool
    assert d["roi"].shape == (n, 4) and d["floor_depth"].shape == (n,)
    assert np.array_equal(d["fg"], d["x"][:, 0] > -1) and np.all(d["x"][:, 0][~d["fg"]] == -1)
    if labels:
        assert d["labels"].shape == (n, size, size) and d["labels"].dtype == np.uint8
        assert not d["labels"][~d["fg"]].any() and d["labels"].max() > 0
    else:
        assert d["labels"] is None


def test_sim_preprocess_config_uses_the_known_bin_and_floor(dataset):
    meta = load_meta(dataset)
    cfg = sim_preprocess_config(dataset)
    assert cfg == sim_preprocess_config(meta)
    known = roi_from_camera(get_camera("default"), SceneConfig().bin)
    assert cfg.roi == known == (58, 58, 166, 166)
    assert cfg.floor_depth == 0.35
    assert sim_preprocess_config(meta, size=32, roi=None).roi is None
    with pytest.raises(ValueError, match="unknown preprocessing keys"):
        sim_preprocess_config(meta, sise=32)


def test_load_sim_split_shapes_and_dtypes(dataset):
    d = load_sim_split(dataset, "test", PreprocessConfig())  # roi, floor filled from meta.json
    check_split(d, 4)
    assert d["config"] == sim_preprocess_config(dataset)
    assert np.all(d["roi"] == (60, 60, 164, 164)) and np.all(d["floor_depth"] == 0.35)
    check_split(load_sim_split(dataset, "train", limit=2, progress=True), 2)
    check_split(load_sim_split(dataset, "train", sim_preprocess_config(dataset, size=32)), 3, 32)
    assert load_sim_split(dataset, "val")["x"].shape == (0, 1, 64, 64)
    with pytest.raises(ValueError, match="unknown split 'dev'"):
        load_sim_split(dataset, "dev")


def test_bag_and_shards_give_the_same_input(dataset):
    cfg = sim_preprocess_config(dataset)
    shards = load_sim_split(dataset, "test", cfg)
    bag = load_bag(BAGS / "cylinder_sim", cfg, limit=4)
    check_split(bag, 4)
    assert bag["stamp_ns"].shape == (4,) and np.all(np.diff(bag["stamp_ns"]) > 0)
    # the bag is 16UC1: 1 mm quantisation moves heights by <= 0.5 mm, x by <= 0.02, and may
    # flip the odd pixel right at the foreground threshold
    both = shards["fg"] & bag["fg"]
    assert (shards["fg"] != bag["fg"]).mean() < 0.005
    assert np.abs(shards["x"][:, 0][both] - bag["x"][:, 0][both]).max() < 0.025
    assert (shards["labels"][both] == bag["labels"][both]).all()


def test_load_bag_finds_the_bin_itself():
    for name, n, shape in [("hex_nut_sim_32fc1", 10, (224, 224)),
                           ("wooden_block_realsense", 6, (480, 848))]:
        d = load_bag(BAGS / name)  # default config: bin and floor found in every frame
        check_split(d, n)
        cam = get_camera("default" if shape[0] == 224 else "realsense_d435")
        known = np.array(roi_from_camera(cam, SceneConfig().bin)) + [2, 2, -2, -2]
        # objects lying against a wall can hide a strip of floor: most frames within 3 px
        err = np.abs(d["roi"] - known).max(1)
        assert np.median(err) <= 3 and err.max() <= 25, err
        assert np.allclose(d["floor_depth"], cam.mount_height, atol=0.001)
        iou = [(f & (lab > 0)).sum() / (f | (lab > 0)).sum()
               for f, lab in zip(d["fg"], d["labels"])]
        assert min(iou) > 0.85  # labels are 0 off the foreground, so this is coverage


def test_load_bag_without_labels(tmp_path):
    from inseggan_ros.io import bags

    frames = bags.read_all(BAGS / "cylinder_sim", limit=2)
    for f in frames:
        f.labels = None
    bags.write_frames(tmp_path / "nolabels", frames)
    check_split(load_bag(tmp_path / "nolabels", PreprocessConfig()), 2, labels=False)
    assert load_bag(tmp_path / "nolabels", limit=0)["x"].shape == (0, 1, 64, 64)


def test_dataset_without_augmentation_is_the_data(dataset):
    d = load_sim_split(dataset, "test")
    ds = DepthTensorDataset(d)
    assert len(ds) == 4
    x = ds[1]
    assert isinstance(x, torch.Tensor) and x.dtype == torch.float32 and x.shape == (1, 64, 64)
    assert np.array_equal(x.numpy(), d["x"][1])
    x, lab = DepthTensorDataset(d, return_labels=True)[2]
    assert lab.shape == (64, 64) and lab.dtype == torch.int64
    assert np.array_equal(lab.numpy(), d["labels"][2])
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=3)))
    assert batch.shape == (3, 1, 64, 64)
    with pytest.raises(ValueError, match=r"rotation -1 invalid; valid: degrees in \[0, 180\]"):
        DepthTensorDataset(d, rotation=-1)
    with pytest.raises(ValueError, match=r"valid: \(N, 1, size, size\)"):
        DepthTensorDataset({"x": d["x"][:, 0]})


def test_flips_are_exact_and_rotations_keep_the_background(dataset):
    d = load_sim_split(dataset, "test")
    torch.manual_seed(0)
    flips = DepthTensorDataset(d, augment=True, return_labels=True)
    seen = set()
    for _ in range(40):
        x, lab = flips[0]
        x0, l0 = torch.from_numpy(d["x"][0]), torch.from_numpy(d["labels"][0]).long()[None]
        variants = {k: (torch.flip(x0, k), torch.flip(l0, k)[0]) for k in [(), (1,), (2,), (1, 2)]}
        match = [k for k, (vx, vl) in variants.items()
                 if torch.equal(x, vx) and torch.equal(lab, vl)]
        assert match, "a flipped sample is no exact flip of the input"
        seen.add(match[0])
    assert len(seen) == 4
    rot = DepthTensorDataset(d, augment=True, rotation=20.0, return_labels=True)
    values = set(d["x"][0].ravel().tolist())
    for _ in range(20):
        x, lab = rot[0]
        assert set(x.numpy().ravel().tolist()) <= values  # nearest: no new depths, -1 stays -1
        assert not lab[x[0] == -1].any()
        assert abs(int((x > -1).sum()) - int(d["fg"][0].sum())) < 0.1 * d["fg"][0].sum()


def test_rotate_by_ninety_degrees_is_rot90():
    x = torch.randn(1, 8, 8)
    labels = torch.randint(0, 5, (1, 8, 8))
    rx, rl = rotate(x, 90, labels)
    assert torch.equal(rx, torch.rot90(x, 1, (1, 2)))
    assert torch.equal(rl, torch.rot90(labels, 1, (1, 2)))
    assert torch.equal(rotate(x, 0)[0], x)
