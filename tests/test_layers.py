"""The layout is the architecture: layers that import only the layers below them (an
import-linter contract over every import, those inside functions included), and a segmenter node
that, serving a frame, loads neither the simulator (pybullet) nor any training code."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

NODE_PROBE = r"""
import json, sys
import numpy as np
import rclpy
from inseggan_ros.ros.segmenter import SegmenterNode
rclpy.init()
node = SegmenterNode()  # loads the default model and segments a warm-up frame
depth = np.full((224, 224), 0.8, np.float32)
depth[90:130, 80:140] = 0.77
node.model(depth)
node.destroy_node()
rclpy.shutdown()
print(json.dumps(sorted(m for m in sys.modules if m.startswith(("inseggan_ros", "pybullet")))))
"""


@pytest.mark.linter
def test_import_contract_holds():
    exe = shutil.which("lint-imports") or str(Path(sys.executable).parent / "lint-imports")
    if not Path(exe).exists():
        pytest.fail("lint-imports not found: install import-linter (requirements.txt)")
    p = subprocess.run([exe, "--config", str(REPO / "setup.cfg"), "--no-cache"],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert p.returncode == 0, p.stdout[-4000:] + p.stderr[-2000:]
    assert "broken" in p.stdout and " 0 broken" in p.stdout


def test_import_contract_fails_on_an_upward_import(tmp_path):
    """The contract is not vacuous: a copy of the package whose runtime imports the training
    code breaks it."""
    exe = shutil.which("lint-imports") or str(Path(sys.executable).parent / "lint-imports")
    copy = tmp_path / "inseggan_ros"
    shutil.copytree(REPO / "inseggan_ros", copy, ignore=shutil.ignore_patterns("__pycache__"))
    target = copy / "runtime" / "picks.py"
    target.write_text(target.read_text() + "\n\ndef _bad():\n"
                      "    from inseggan_ros.learning import train  # noqa: F401\n")
    shutil.copy(REPO / "setup.cfg", tmp_path / "setup.cfg")
    p = subprocess.run([exe, "--config", str(tmp_path / "setup.cfg"), "--no-cache"],
                       capture_output=True, text=True, cwd=tmp_path, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(tmp_path)})
    assert p.returncode != 0
    assert "inseggan_ros.runtime.picks -> inseggan_ros.learning.train" in p.stdout


def test_the_segmenter_node_loads_no_simulator_and_no_training_code():
    p = subprocess.run([sys.executable, "-c", NODE_PROBE], capture_output=True, text=True,
                       timeout=180)
    assert p.returncode == 0, p.stderr[-3000:]
    loaded = json.loads(p.stdout.strip().splitlines()[-1])
    assert "inseggan_ros.runtime.segment" in loaded  # the probe did load the model
    banned = [m for m in loaded if m.startswith(("pybullet", "inseggan_ros.sim",
                                                 "inseggan_ros.learning", "inseggan_ros.data",
                                                 "inseggan_ros.evaluation", "inseggan_ros.cli"))]
    assert banned == []
