"""`tools/device_train.py pack`: a recording packed as `inseggan loop --bag` learns its shape
from it, read back by `unpack` (what the GPU machine trains on)."""
from __future__ import annotations

import sys

import numpy as np
import pytest
from conftest import BAGS, REPO

sys.path.insert(0, str(REPO / "tools"))

import device_train  # noqa: E402


def test_a_recording_packs_as_the_loop_reads_it(tmp_path):
    from inseggan_ros.learning.loop import BagFrames
    from inseggan_ros.runtime.preprocess import PreprocessConfig

    bag, out = BAGS / "cone_sim", tmp_path / "cone.npz"
    assert device_train.main(["pack", "--bag", str(bag), "--instances", "5",
                              "--out", str(out)]) == 0
    tr, val, prep, info = device_train.unpack(out)
    before, held = BagFrames(bag, 5).frames(PreprocessConfig())
    np.testing.assert_array_equal(tr["x"], before["x"].astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(val["fg"], held["fg"])
    assert tr["labels"] is None and val["labels"] is None  # nothing of the labels is packed
    assert info["instances"] == 5 and info["source"] == "bag"
    assert info["camera"]["width"] > 0


@pytest.mark.parametrize("argv, message", [
    ([], "give --data"),
    (["--bag", "b", "--data", "d"], "give --data"),
    (["--bag", "b"], "needs --instances"),
    (["--bag", "b", "--instances", "5", "--with-labels"], "no labels to pack"),
    (["--bag", "b", "--instances", "5", "--train-frames", "9"], "no --train-frames")])
def test_pack_says_what_it_needs(tmp_path, argv, message):
    with pytest.raises(SystemExit, match=message):
        device_train.main(["pack", *argv, "--out", str(tmp_path / "x.npz")])
