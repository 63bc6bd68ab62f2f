"""`inseggan simulate`: shards, splits, determinism across worker counts, bags, atomic output."""
import json
import subprocess
import sys

import numpy as np
from conftest import REPO, refused, run_cli

from inseggan_ros.io import bags
from inseggan_ros.sim.dataset import iter_scenes, load_meta, scene_seed
from inseggan_ros.sim.scene import BinSimulator, SceneConfig


def test_simulate_splits_shards_and_bags(tmp):
    out = tmp / "ds"
    p = run_cli("simulate", "--quiet", "--object", "stopper", "--count", "20", "--split",
                "0.6,0.2,0.2", "--shard-size", "5", "--workers", "2", "--seed", "3", "--bags",
                "--out", out, check=True)
    assert "simulated 20 scenes" in p.stdout and "scenes/s" in p.stdout
    meta = load_meta(out)
    assert meta["counts"] == {"train": 12, "val": 4, "test": 4}
    assert [s["scenes"] for s in meta["shards"]["train"]] == [5, 5, 2]
    assert meta["scene"]["object"] == "stopper"
    assert meta["repiled_scenes"] == 0 and "piled again" not in p.stdout
    test = list(iter_scenes(out, "test"))
    assert len(test) == 4
    # scene i of a split is scene_seed(seed, split, i), whatever the worker that made it
    cfg = SceneConfig.from_dict(meta["scene"])
    with BinSimulator(cfg) as sim:
        again = sim.render(scene_seed(3, "test", 2))
    np.testing.assert_array_equal(test[2][0], again.depth)
    np.testing.assert_array_equal(test[2][1], again.labels)
    # the bag of a split holds the same frames
    frames = bags.read_all(out / meta["bags"]["test"])
    assert len(frames) == 4
    np.testing.assert_allclose(frames[2].metres(), again.depth, atol=0.0005)
    np.testing.assert_array_equal(frames[2].labels, again.labels)
    assert not [p for p in tmp.iterdir() if p.name.startswith(".")], "temporary files left"


def test_one_worker_and_two_workers_make_the_same_data_set(tmp):
    for w in (1, 2):
        run_cli("simulate", "--quiet", "--count", "6", "--shard-size", "2", "--workers", w,
                "--out", tmp / f"w{w}", check=True)
    for split in ("train", "val", "test"):
        a, b = list(iter_scenes(tmp / "w1", split)), list(iter_scenes(tmp / "w2", split))
        assert len(a) == len(b)
        for (da, la), (db, lb) in zip(a, b):
            assert np.array_equal(da, db) and np.array_equal(la, lb)


def test_existing_output_and_bad_arguments(tmp):
    out = tmp / "ds"
    run_cli("simulate", "--quiet", "--count", "2", "--out", out, check=True)
    before = json.loads((out / "meta.json").read_text())
    p = refused("simulate", "--quiet", "--count", "2", "--out", out)
    assert p.returncode == 2 and "exists already" in p.stderr and "--overwrite" in p.stderr
    assert json.loads((out / "meta.json").read_text()) == before
    for args, message in [(["--count", "0"], "count must be >= 1"),
                          (["--split", "0.8,0.2"], "need three fractions"),
                          (["--instances", "40"], "instances must be in 0..20"),
                          (["--workers", "0"], "workers must be >= 1")]:
        p = refused("simulate", "--quiet", *args, "--out", tmp / "bad")
        assert p.returncode == 2 and message in p.stderr, p.stderr
        assert "Traceback" not in p.stderr
        assert not (tmp / "bad").exists()


def test_bench_sim_prints_throughput(tmp):
    """`python -m tools.bench_sim` (`make bench`; not an `inseggan` command: the package never
    imports tools/)."""
    p = subprocess.run([sys.executable, "-m", "tools.bench_sim", "--scenes", "10", "--workers",
                        "2", "--json", str(tmp / "b.json")], cwd=REPO, capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert "scenes/s" in p.stdout
    r = json.loads((tmp / "b.json").read_text())
    assert r["one_core_scenes_per_s"] > 0 and r["parallel_scenes_per_s"] > 0


def test_contact_sheet_png(tmp):
    run_cli("contact-sheet", "--out", tmp / "sheet.png", check=True)
    data = (tmp / "sheet.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
