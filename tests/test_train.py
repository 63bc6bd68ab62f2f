"""Real (tiny) training runs: it learns, checkpoints round-trip, a killed run resumes,
DDP agrees."""
import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch
from conftest import installed_executable, refused, run_cli

from inseggan_ros.core import checkpoint
from inseggan_ros.runtime.segment import Segmenter

# the shipped models' config (an explicit template), 8 wide: well conditioned, so that 120
# iterations improve the reconstruction on any CPU (the learned renderer at this size barely moved:
# 0.755 -> 0.750 on one machine, 0.760 -> 0.721 at 80 iterations on another)
TINY = ["--config", "cpu_spheres", "--nf", "8", "--batch-size", "8", "--instances", "5", "--quiet",
        "--device", "cpu"]


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("data") / "cyl"
    run_cli("simulate", "--quiet", "--count", "80", "--split", "0.8,0.1,0.1", "--workers", "2",
            "--out", out, check=True)
    return out


def _val(log):
    return [r for r in map(json.loads, log.read_text().splitlines()) if r["kind"] == "val"]


def test_tiny_training_run_improves_reconstruction(tmp, tiny_data):
    out = tmp / "run"
    p = run_cli("train", "--data", tiny_data, "--out", out, "--iterations", "120",
                "--eval-every", "40", *TINY, timeout=600, check=True)
    assert "trained 120 iterations" in p.stdout
    val = _val(out / "log.jsonl")
    assert [v["iteration"] for v in val] == [0, 40, 80, 120]  # 0: before any training
    first, last = val[0]["recon_l1"], val[-1]["recon_l1"]
    # measured: 0.721 -> 0.595, 0.629, 0.545 at 40, 80, 120 iterations (0.76 x the start)
    assert last < 0.9 * first, f"encoder reconstruction error did not improve: {first} -> {last}"
    assert all("miou" in v and 0 <= v["miou"] <= 1 for v in val)
    # measured: 0.439 -> 0.496, 0.450, 0.519 (the untrained rods already cover some objects)
    assert max(v["miou"] for v in val[1:]) > val[0]["miou"]
    for name in ("best.pt", "last.pt", "curves.png", "summary.json", "config.json"):
        assert (out / name).is_file(), name
    assert len(list((out / "samples").glob("*.png"))) == 4
    # checkpoint round trip: a checkpoint alone rebuilds the model and gives the same output
    state = checkpoint.load(out / "last.pt")
    assert state["iteration"] == 120 and state["model_config"]["nf"] == 8
    seg = Segmenter.from_checkpoint(out / "last.pt", device="cpu")
    x = torch.zeros(2, 1, 64, 64) - 1
    x[:, :, 20:30, 20:40] = 0.3
    a = seg.segment_batch(x)["reconstruction"]
    b = Segmenter.from_checkpoint(out / "last.pt", device="cpu").segment_batch(x)["reconstruction"]
    torch.testing.assert_close(a, b)
    half = checkpoint.export_for_inference(out / "last.pt", tmp / "model_fp16.pt", half=True)
    assert half.stat().st_size < 0.5 * (out / "last.pt").stat().st_size
    c = Segmenter.from_checkpoint(half, device="cpu").segment_batch(x)["reconstruction"]
    assert (a - c).abs().max() < 0.05


def test_killed_run_resumes_from_its_last_checkpoint(tmp, tiny_data):
    out = tmp / "run"
    args = [str(installed_executable("inseggan")), "train", "--data", str(tiny_data), "--out",
            str(out), "--iterations", "1000", "--eval-every", "5", *TINY]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 300:
            if (out / "last.pt").exists() and checkpoint.load(out / "last.pt")["iteration"] >= 10:
                break
            time.sleep(0.5)
        proc.send_signal(signal.SIGKILL)  # no chance to clean up
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
    saved = checkpoint.load(out / "last.pt")["iteration"]
    assert saved >= 10
    assert not [p for p in out.iterdir() if ".tmp" in p.name], "half-written files left"
    p = run_cli("train", "--data", tiny_data, "--out", out, "--iterations", str(saved + 5),
                "--eval-every", "5", "--resume", *TINY, timeout=600, check=True)
    assert f"at iteration {saved}" in p.stdout
    assert checkpoint.load(out / "last.pt")["iteration"] == saved + 5
    # without --resume the run is protected
    p = refused("train", "--data", tiny_data, "--out", out, "--iterations", "5", *TINY)
    assert p.returncode == 2 and "--resume" in p.stderr


def test_ddp_two_processes_gloo_identical_weights(tmp, tiny_data):
    out = tmp / "ddp"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    torchrun = os.path.join(os.path.dirname(sys.executable), "torchrun")
    p = subprocess.run([torchrun, "--nproc_per_node", "2",
                        "--master_port", str(29500 + os.getpid() % 500),
                        "-m", "inseggan_ros.cli.main", "train", "--data", str(tiny_data), "--out",
                        str(out), "--iterations", "6", "--eval-every", "6", *TINY],
                       capture_output=True, text=True, timeout=600, env=env)
    assert p.returncode == 0, p.stderr[-3000:]
    assert p.stdout.count("trained 6 iterations") == 1, p.stdout  # rank 0 reports for both
    summary = json.loads((out / "summary.json").read_text())
    assert summary["world_size"] == 2 and summary["iterations"] == 6
    sums = summary["weights_sha256_per_rank"]
    assert len(sums) == 2 and sums[0] == sums[1], "ranks disagree after DDP training"


def test_n_is_the_data_sets_parts_per_bin_unless_given(tmp):
    """A simulated data set says how many parts its bins hold; a model of 5 instances fitted to
    bins of 4 would render a part too many in every frame."""
    data = tmp / "four"
    run_cli("simulate", "--quiet", "--instances", "4", "--count", "10", "--split", "0.6,0.4,0",
            "--workers", "1", "--out", data, check=True)
    i = TINY.index("--instances")
    tiny = TINY[:i] + TINY[i + 2:]  # TINY without its n
    for extra, n in (([], 4), (["--instances", "3"], 3)):
        out = tmp / f"run{n}"
        run_cli("train", "--data", data, "--out", out, "--iterations", "1", "--eval-every", "1",
                *tiny, *extra, timeout=600, check=True)
        assert checkpoint.load(out / "last.pt")["model_config"]["n_instances"] == n


def test_best_checkpoint_is_the_best_validation_even_the_starting_point(tmp, tiny_data):
    """best.pt holds the weights of the best validation in the log. A run whose starting point is
    never beaten (learning rates too small to move a weight, as a run that does not learn) keeps
    its starting weights, not its last ones under the starting point's score and tau."""
    from inseggan_ros.data.datasets import load_sim_training
    from inseggan_ros.learning.train import get_config, train

    tr, val, prep, info = load_sim_training(tiny_data, None, None, progress=False)
    cfg = get_config("cpu_spheres", nf=8, batch_size=8, n_instances=5, max_iterations=3,
                     eval_every=40, lr_g=1e-12, lr_d=1e-12, lr_e=1e-12)
    out = tmp / "run"
    train(cfg, tr, val, out, prep.to_dict(), info, device="cpu", progress=False)  # as the CLI
    val_log = _val(out / "log.jsonl")
    assert [v["iteration"] for v in val_log] == [0, 3]  # the start, then the end of the budget
    best = max(val_log, key=lambda v: v["miou"])  # the first of equal scores: only > improves
    state = checkpoint.load(out / "best.pt")
    assert state["iteration"] == best["iteration"]
    assert state["best"] == best["miou"] and state["tau"] == best["tau"]
