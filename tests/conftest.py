"""Shared test set-up: DDS stays on this machine, in a domain of this test run's own."""
import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(os.getpid() % 90 + 5))

REPO = Path(__file__).resolve().parents[1]
BAGS = REPO / "bags"


def installed_executable(name: str) -> Path:
    """Where `ros2 run inseggan_ros <name>` finds the executable:
    <prefix>/lib/inseggan_ros/<name>."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix

    try:
        prefix = get_package_prefix("inseggan_ros")
    except PackageNotFoundError:
        pytest.fail("inseggan_ros is not on AMENT_PREFIX_PATH: build it with colcon and "
                    "`source install/setup.bash` (make test does both)")
    return Path(prefix) / "lib" / "inseggan_ros" / name


def checkpoint_without_settings(path: Path) -> Path:
    """The shipped cylinder model without its stored settings, as a training checkpoint has
    none, written to `path`."""
    from inseggan_ros.core import checkpoint

    state = checkpoint.load(REPO / "models" / "cylinder" / "model.pt")
    del state["inference"]
    return checkpoint.save(path, state)


def run_cli(*args, timeout=300, check=False) -> subprocess.CompletedProcess:
    """Run the installed `inseggan` command."""
    proc = subprocess.run([str(installed_executable("inseggan")), *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)
    if check and proc.returncode != 0:
        raise AssertionError(f"inseggan {args} failed ({proc.returncode}):\n{proc.stderr}")
    return proc


def _param_client(*args) -> str:
    p = subprocess.run([sys.executable, str(Path(__file__).parent / "param_client.py"),
                        *map(str, args)], capture_output=True, text=True, timeout=90)
    return p.stdout.strip()


def set_param(node: str, name: str, value: str) -> str:
    """Set a running node's parameter from another process (value: a Python literal)
    -> 'ok' or 'rejected: <reason>'."""
    return _param_client("set", node, name, value)


def set_params(node: str, *pairs: tuple[str, str]) -> list[str]:
    """`set_param` for each (name, value) in turn, one request each, from one process (a
    process per set costs a second or two of start-up and discovery) -> a result per pair."""
    return _param_client("set", node, *(v for pair in pairs for v in pair)).splitlines()


def get_params(node: str, *names: str) -> dict:
    """A running node's parameters, read from another process."""
    import json

    return json.loads(_param_client("get", node, *names))


@pytest.fixture
def tmp(tmp_path):
    return tmp_path


@pytest.fixture(scope="session")
def tiny_model(tmp_path_factory):
    """A tiny model as `inseggan train` leaves it (learned renderer, 10 iterations) and the
    simulated data set it was trained on: root/run/best.pt, root/data."""
    root = tmp_path_factory.mktemp("seg")
    run_cli("simulate", "--quiet", "--count", "40", "--split", "0.5,0.25,0.25", "--out",
            root / "data", check=True)
    run_cli("train", "--data", root / "data", "--out", root / "run", "--iterations", "10",
            "--eval-every", "10", "--config", "cpu", "--nf", "8", "--batch-size", "4",
            "--quiet", "--device", "cpu", check=True, timeout=600)
    return root


@pytest.fixture(scope="module")
def cylinder_bag():
    """The shipped cylinder model (one torch thread) and its labelled sample bag's frames; one
    per test module, which may change the model's settings."""
    import torch

    from inseggan_ros.data import datasets as data
    from inseggan_ros.runtime.segment import Segmenter

    torch.set_num_threads(1)
    seg = Segmenter.from_checkpoint(REPO / "models" / "cylinder" / "model.pt", device="cpu")
    seg.inference = zbuffer_settings(seg.inference)
    return seg, data.load_bag(BAGS / "cylinder_sim", seg.prep_cfg)


def zbuffer_settings(cfg):
    """realtime.yaml over a model's settings, with the z-buffer's labels (`centre_votes: off`):
    what the shipped cylinder ran before its centre votes, for the tests of what comes after
    the z-buffer (tau, the vote, the split; over centre votes there is no vote, and one
    starting point: their own tests are test_centres.py)."""
    from inseggan_ros.core import settings

    return replace(settings.apply_file(cfg, "realtime"), centre_votes="off")


@pytest.fixture(scope="session")
def python():
    return sys.executable


def which(name):
    return shutil.which(name)


# The test files that train or simulate the most, longest first: collected before the others so
# that, when pytest-xdist shares the files between processes (scripts/test.sh), none of them
# starts last and leaves the other process idle.
LONGEST_FIRST = ("test_loop.py", "test_distill.py", "test_train.py", "test_unlabelled.py",
                 "test_label_head.py", "test_selffit.py", "test_models.py", "test_template.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: file order kept
