"""Bins that hold fewer parts than the model's n, down to none: scenes of a given count, a
count drawn per scene, and data sets of mixed counts (a robot empties the bin it picks from)."""
import json

import numpy as np
import pytest
from conftest import refused, run_cli

from inseggan_ros.sim.dataset import DatasetSpec, generate, iter_scenes, load_meta, scene_seed
from inseggan_ros.sim.scene import BinSimulator, SceneConfig


def test_an_empty_bin_has_all_zero_labels_no_poses_and_its_floor():
    cfg = SceneConfig(object="bolt", instances=0)
    with BinSimulator(cfg) as sim:
        scene = sim.render(4)
    cam = cfg.camera
    assert scene.labels.shape == (cam.height, cam.width) and scene.labels.dtype == np.uint8
    assert not scene.labels.any()
    assert scene.poses.shape == (0, 7)
    # the bin's floor seen straight down from the camera's height, nothing on it
    u, v = int(round(cam.cx)), int(round(cam.cy))
    assert scene.depth[v - 20:v + 20, u - 20:u + 20] == pytest.approx(cam.mount_height, abs=1e-3)


@pytest.mark.parametrize("count", [1, 2])
def test_a_bin_of_fewer_parts_holds_that_many(count):
    with BinSimulator(SceneConfig(object="hex_nut", instances=count)) as sim:
        scene = sim.render(11)
    assert scene.poses.shape == (count, 7)
    assert set(np.unique(scene.labels)) == set(range(count + 1))


def test_a_drawn_count_follows_the_seed_and_keeps_the_piles():
    """`min_instances`: each scene's count is drawn from its seed alone, over the whole range;
    a scene whose drawn count is n is the same pile as the fixed-count scene of that seed
    (the count's draw takes none of the pile's random numbers)."""
    cfg = SceneConfig(object="stopper", instances=4, min_instances=0)
    counts = [cfg.count(s) for s in range(60)]
    assert counts == [cfg.count(s) for s in range(60)]
    assert set(counts) == {0, 1, 2, 3, 4}
    assert SceneConfig(object="stopper", instances=4).count(7) == 4
    full = next(s for s in range(60) if cfg.count(s) == 4)
    small = next(s for s in range(60) if cfg.count(s) == 1)
    with BinSimulator(cfg) as mixed, \
            BinSimulator(SceneConfig(object="stopper", instances=4)) as four:
        a, one = mixed.render(full), mixed.render(small)
        np.testing.assert_array_equal(a.depth, four.render(full).depth)
        np.testing.assert_array_equal(a.labels, four.render(full).labels)
    assert len(a.poses) == 4 and len(one.poses) == 1 and one.labels.max() == 1


def test_old_scene_configs_load_with_one_count_per_scene():
    d = SceneConfig(object="cone", instances=3).to_dict()
    del d["min_instances"]  # a data set made before the field existed
    cfg = SceneConfig.from_dict(json.loads(json.dumps(d)))
    assert cfg.min_instances is None and cfg.count(123) == 3


def test_a_data_set_of_mixed_counts(tmp):
    spec = DatasetSpec(SceneConfig(object="cylinder", instances=3, min_instances=0),
                       {"train": 10, "test": 4}, seed=5, shard_size=4)
    meta = generate(spec, tmp / "ds", workers=1, progress=False)
    assert load_meta(tmp / "ds")["instance_counts"] == meta["instance_counts"]
    for split in ("train", "test"):
        seeds = [scene_seed(5, split, i) for i in range(spec.counts[split])]
        want = [spec.scene.count(s) for s in seeds]
        hist = {str(c): want.count(c) for c in sorted(set(want))}
        assert meta["instance_counts"][split] == hist
        got = []
        for shard in meta["shards"][split]:
            with np.load(tmp / "ds" / shard["file"]) as z:
                assert z["poses"].shape[1:] == (3, 7)
                for n, poses in zip(z["instances"], z["poses"]):
                    assert np.isfinite(poses[:n]).all() and np.isnan(poses[n:]).all()
                got += list(z["instances"])
        assert got == want
        for (depth, labels), n in zip(iter_scenes(tmp / "ds", split), want):
            assert labels.max() <= n and (n > 0 or not labels.any())
    assert 0 in [spec.scene.count(scene_seed(5, s, i)) for s in ("train", "test")
                 for i in range(spec.counts[s])], "the seeds chosen hold an empty bin"


def test_simulate_draws_a_count_per_scene_from_the_command_line(tmp):
    """`simulate --min-instances M`: the scenes of one data set hold M..--instances parts,
    each scene's own; a range that cannot be is refused with what is valid."""
    run_cli("simulate", "--quiet", "--object", "hex_nut", "--instances", "3", "--min-instances",
            "0", "--count", "12", "--split", "12,0,0", "--seed", "5", "--workers", "1", "--out",
            tmp / "ds", check=True, timeout=300)
    meta = load_meta(tmp / "ds")
    assert meta["scene"]["min_instances"] == 0
    counts = {int(k) for k in meta["instance_counts"]["train"]}
    assert len(counts) > 1 and counts <= {0, 1, 2, 3}, counts
    p = refused("simulate", "--quiet", "--instances", "3", "--min-instances", "4", "--count",
                "4", "--out", tmp / "bad")
    assert p.returncode == 2 and "min_instances must be in 0..instances (3)" in p.stderr, p.stderr
    assert not (tmp / "bad").exists()
