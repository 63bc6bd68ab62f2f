"""Centre votes: each instance found by its pixels' votes for its centre, taught on simulated piles.

The encoder reads n poses from the whole 64 x 64 frame in one pass, a global regression whose
placements are a few pixels off; even an encoder taught on piles of the *true* part stays about
0.04 above Felzenszwalb on the cylinder, and most of what it loses is where the renders sit
(docs/experiments.md, 2026-11-28). A small fully convolutional network reads positions locally
instead (the instance branch of Panoptic-DeepLab, Cheng et al. 2020): for every pixel a heatmap
of part centres (the mean of each part's visible pixels) and the offset from the pixel to its
part's centre. The heatmap's peaks (at most n) are the instances, and each foreground pixel
joins the peak nearest where its offset points.

It is taught on the loop's labelled piles of the *learned* part (`inseggan loop`, `inseggan
simulate --object MODEL`): no label of the user's frames is read. The 8 symmetries of the square
augment it. At test time (`InferenceConfig.centre_votes: on`) its instances replace the
z-buffer's labels, each given the id of the render it overlaps most (so scores, masks and picks
keep the renders' meaning); the encoder, the renders and the reconstruction stay as they are, and
the labels then go through the smoothing and the split. The superpixel vote is skipped: these
labels already follow the heights, and the vote cost them mIoU on the cylinder's validation
split (docs/experiments.md, 2026-11-28, night).

    net = CentreNet()
    labels = centre_labels(net, x, fg, n)        # (B, 64, 64) uint8, 0 = background
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from inseggan_ros.evaluation.evaluate import write_json
from inseggan_ros.runtime.symmetry import SYMMETRIES, transform_image
from inseggan_ros.runtime.centres import (  # noqa: F401  (the net, shared with inference)
    HEAT_SIGMA, MIN_PIXELS, OFFSET_UNIT, PEAK_RADIUS, PEAK_THRESHOLD, CentreNet, _grid,
    centre_labels, decode, match_to_renders, net_from_state, net_input, net_state)


@dataclass(frozen=True)
class CentreConfig:
    width: int = 16  # channels at 64 x 64; 2x and 4x that at 32 x 32 and 16 x 16
    iterations: int = 3000
    batch: int = 32
    lr: float = 2e-3  # Adam, one-cycle schedule (a short warm-up, then cosine down)
    eval_every: int = 500
    seed: int = 0

    def __post_init__(self):
        from inseggan_ros.learning.label_head import check_training
        check_training(self)
        if self.iterations < 4:  # fewer leave the one-cycle schedule a phase of no steps
            raise ValueError(f"iterations {self.iterations!r} invalid; valid: >= 4 (a warm-up "
                             "and a decay)")


def targets(labels: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, H, W) labels (0 = background, 1..n) -> the heatmap (B, H, W) (a Gaussian of
    HEAT_SIGMA round each part's centre, the mean of its pixels) and the offsets (B, 2, H, W)
    from each labelled pixel to its part's centre, in OFFSET_UNIT pixels (0 on background)."""
    H, W = labels.shape[-2:]
    onehot = F.one_hot(labels.long(), n + 1).permute(0, 3, 1, 2)[:, 1:].float()  # (B, n, H, W)
    ys, xs = _grid(H, W)
    count = onehot.sum((2, 3))
    cy = (onehot * ys).sum((2, 3)) / count.clamp_min(1)
    cx = (onehot * xs).sum((2, 3)) / count.clamp_min(1)
    dy, dx = cy[..., None, None] - ys, cx[..., None, None] - xs  # (B, n, H, W)
    heat = (torch.exp(-(dy ** 2 + dx ** 2) / (2 * HEAT_SIGMA ** 2))
            * (count >= MIN_PIXELS)[..., None, None]).amax(1)
    offsets = torch.stack([(dy * onehot).sum(1), (dx * onehot).sum(1)], 1) / OFFSET_UNIT
    return heat, offsets


def loss_terms(pred: torch.Tensor, labels: torch.Tensor, n: int) -> tuple[torch.Tensor, ...]:
    """The heatmap's squared error (weighted up near centres) and the offsets' L1 on the
    labelled pixels."""
    heat, offsets = targets(labels, n)
    l_heat = 10 * ((1 + 10 * heat) * (torch.sigmoid(pred[:, 0]) - heat) ** 2).mean()
    mask = (labels > 0).float()
    l_off = ((pred[:, 1:] - offsets).abs().sum(1) * mask).sum() / mask.sum().clamp_min(1)
    return l_heat, l_off


def miou_of(pred: np.ndarray, gt: np.ndarray) -> float:
    from inseggan_ros.core.metrics import mean_miou, miou_batch
    return float(mean_miou(miou_batch(pred, gt)))


def step_seconds(cfg: CentreConfig = CentreConfig(), size: int = 64, n: int = 5,
                 steps: int = 4) -> float:
    """Seconds one of `train_net`'s iterations takes on this machine: `steps` of them timed,
    after one to warm up, on a batch of `cfg.batch` empty frames of `size` x `size` with a
    square part each (the time does not depend on what the frames hold). What a time budget
    turns into iterations (`budget.centre_iterations`)."""
    torch.manual_seed(cfg.seed)
    net = CentreNet(cfg.width)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    X = torch.zeros(cfg.batch, 2, size, size)
    L = torch.zeros(cfg.batch, size, size, dtype=torch.int64)
    L[:, size // 4:size // 2, size // 4:size // 2] = 1
    X[:, 1] = (L > 0).float()
    t0 = 0.0
    for k in range(steps + 1):
        if k == 1:
            t0 = time.perf_counter()
        l_heat, l_off = loss_terms(net(X), L, n)
        opt.zero_grad(set_to_none=True)
        (l_heat + l_off).backward()
        opt.step()
    return (time.perf_counter() - t0) / steps


def train_net(train: dict, val: dict, n: int, out, cfg: CentreConfig = CentreConfig(),
              progress: bool = True) -> dict:
    """A `CentreNet` fitted to labelled frames: `train` and `val` = {"x", "fg", "labels"}
    (`data.load_sim_split`), n instances a frame. Every `eval_every` iterations the validation
    frames' mIoU of the decoded labels is measured and out/last.pt written (the net, the
    optimiser, the history: a killed run started again resumes from it); out/net.pt is the
    best on validation. Also out/summary.json and out/curves.png. -> the summary."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    net = CentreNet(cfg.width)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.OneCycleLR(
        opt, cfg.lr, total_steps=cfg.iterations, pct_start=max(0.05, 2 / cfg.iterations))
    gen = torch.Generator().manual_seed(cfg.seed)
    X, L = net_input(train["x"], train["fg"]), torch.from_numpy(train["labels"].astype(np.int64))
    Xv = net_input(val["x"], val["fg"])
    history, best, start, seconds = [], -1.0, 0, 0.0
    last = out / "last.pt"
    if last.is_file():
        state = torch.load(last, weights_only=False)
        if state["config"] != asdict(cfg):
            raise ValueError(f"{last}: made with other settings ({state['config']}); valid: "
                             "the same settings, or a new output folder")
        net.load_state_dict(state["net"])
        opt.load_state_dict(state["opt"])
        sched.load_state_dict(state["sched"])
        gen.set_state(state["gen"])
        history, best, start, seconds = (state["history"], state["best"], state["iteration"],
                                         state["seconds"])

    def score() -> float:
        net.eval()
        pred = torch.cat([centre_labels(net, Xv[i:i + 100, :1], Xv[i:i + 100, 1] > 0, n)
                          for i in range(0, len(Xv), 100)])
        net.train()
        return miou_of(pred.numpy(), val["labels"])

    t0 = time.monotonic() - seconds
    bar = tqdm(range(start + 1, cfg.iterations + 1), desc="centre votes", unit="it",
               initial=start, total=cfg.iterations, disable=not progress)
    for it in bar:
        idx = torch.randint(0, len(X), (cfg.batch,), generator=gen)
        sym = SYMMETRIES[int(torch.randint(0, len(SYMMETRIES), (1,), generator=gen))]
        l_heat, l_off = loss_terms(net(transform_image(X[idx], sym)),
                                   transform_image(L[idx], sym), n)
        loss = l_heat + l_off
        l_heat, l_off = float(l_heat.detach()), float(l_off.detach())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        bar.set_postfix(loss=f"{l_heat + l_off:.3f}")
        if it % 50 == 0:
            history.append({"kind": "train", "iteration": it, "heat": l_heat,
                            "offset": l_off})
        if it % cfg.eval_every == 0 or it == cfg.iterations:
            m = score()
            history.append({"kind": "val", "iteration": it, "val_miou": m})
            bar.write(f"iteration {it}: validation mIoU {m:.4f}")
            if m > best:
                best = m
                torch.save(net_state(net), out / ".net.pt.tmp")
                (out / ".net.pt.tmp").replace(out / "net.pt")
            torch.save({"config": asdict(cfg), "net": net.state_dict(), "opt": opt.state_dict(),
                        "sched": sched.state_dict(), "gen": gen.get_state(),
                        "history": history, "best": best, "iteration": it,
                        "seconds": time.monotonic() - t0}, out / ".last.pt.tmp")
            (out / ".last.pt.tmp").replace(last)
            _plot(history, out / "curves.png")
    bar.close()
    summary = {"config": asdict(cfg), "seconds": round(time.monotonic() - t0, 1),
               "best_val_miou": best, "history": history, "train_frames": int(len(X)),
               "val_frames": int(len(Xv))}
    write_json(out / "summary.json", summary)
    return summary


def _plot(history: list, path) -> None:
    from inseggan_ros.core.viz import plot_history

    plot_history(history, path, [("losses (training)", "train", ("heat", "offset")),
                                 ("piles' validation mIoU", "val", ("val_miou",))])


def fit(model, sim, out, cfg: CentreConfig = CentreConfig(), frames: int | None = None,
        progress: bool = True, as_given: bool = False, self_labels: bool = False,
        held_out: int = 200, workers: int = 1, user_frames: dict | None = None,
        teacher_votes: bool = False, teacher_settings: str = "own",
        pasted=None) -> dict:
    """Centre votes for `model` (a checkpoint) from the labelled scenes of the simulated data
    set `sim` (train split to learn from, val split to choose the best iteration), cut as the
    model's preprocessing cuts frames (`as_given`: as a bag's, the bin found in every frame):
    out/net.pt, out/summary.json, out/curves.png, and out/model.pt, the model with the net
    and its settings switched to it (`centre_votes: on`). -> the summary, with "model".

    With `self_labels`, `sim` is instead the user's own data set (its train split) or
    recording (a bag: all its frames), whose frames (their labels are not read) are labelled
    by the model itself with its own settings (or `teacher_settings`: a parameters file or a
    shipped one's name; centre votes off, or with `teacher_votes` on: the model as it ships,
    its own net the teacher; in `workers` processes), the last
    `held_out` of them kept out to choose the best iteration by. Where the learned part
    is not the real one, piles of it teach the net the wrong part (the nut: validation 0.805
    against the shipped 0.886), its own frames the right one (0.922; docs/experiments.md,
    2026-11-29). The labels are saved chunk by chunk in out/self_labels.npz, and a killed run
    resumes them. `user_frames` ({x, fg}, cut as the model cuts them), where given, are those
    frames instead of `sim`'s (which then only names them: the loop's bag frames before its
    held-out cut).

    With `pasted` (a `pasted.PasteConfig`), the piles are instead pasted from the parts seen
    whole in `user_frames` (`learning.pasted`): no template and no label; the card says how
    many parts were found."""
    from dataclasses import replace

    from inseggan_ros.core import checkpoint
    from inseggan_ros.data.datasets import load_sim_split
    from inseggan_ros.runtime.segment import Segmenter
    from inseggan_ros.core.settings import InferenceConfig

    out = Path(out)
    state = checkpoint.load(model)
    seg = Segmenter.from_checkpoint(model, device="cpu")
    n = seg.model_cfg.n_instances
    _check_teacher(model, seg, self_labels, teacher_votes, teacher_settings)
    if pasted is not None:
        from inseggan_ros.learning.pasted import paste_splits
        if self_labels or user_frames is None:
            raise ValueError("pasted piles need the user's frames (user_frames) and no "
                             "self-labels; valid: one teacher")
        splits = paste_splits(user_frames, n, seg.prep_cfg, pasted)
    elif self_labels:
        splits = _self_labelled(model, seg, sim, out, frames, held_out, workers, progress,
                                user_frames, teacher_votes, teacher_settings)
    else:
        splits = {}
        for split in ("train", "val"):
            splits[split] = load_sim_split(sim, split, seg.prep_cfg, limit=frames,
                                           progress=progress, as_given=as_given)
            if len(splits[split]["x"]) == 0:
                raise ValueError(f"{sim}: no scenes in its {split} split; valid: a simulated "
                                 "data set with train and val scenes (`inseggan simulate`, the "
                                 "loop's out/sim)")
    summary = train_net(splits["train"], splits["val"], n, out, cfg, progress)
    net = net_from_state(torch.load(out / "net.pt", weights_only=True))
    inference = replace(InferenceConfig.from_dict(state.get("inference", {})),
                        centre_votes="on", label_head="off")  # the votes instead of a head
    keep = {k: v for k, v in state.items() if k not in ("format", "optimizers", "rng")}
    teacher = ("pasted piles" if pasted is not None else
               ("self-labels" if self_labels else "piles")
               + (" with its centre votes" if teacher_votes else ""))
    keep.update(centre_net={**net_state(net), "sim": str(sim),
                            "piles_part": (None if self_labels else
                                           f"{splits['parts']} parts seen whole in the user's "
                                           "frames" if pasted is not None else piles_part(sim)),
                            "teacher": teacher,
                            "teacher_settings": teacher_settings if self_labels else None,
                            "summary": {k: v for k, v in summary.items() if k != "history"}},
                inference=inference.to_dict())
    checkpoint.save(out / "model.pt", keep)
    return {**summary, "model": str(out / "model.pt")}


def _check_teacher(model, seg, self_labels: bool, teacher_votes: bool,
                   teacher_settings: str) -> None:
    """What `fit` refuses of the self-labels' teacher, before any frame is read."""
    if teacher_votes and not self_labels:
        raise ValueError("the teacher's centre votes (--teacher-centre-votes) without "
                         "self-labels: piles carry their own labels; valid: with "
                         "--self-labels, or without the teacher's votes")
    if teacher_settings != "own":
        from inseggan_ros.learning.selffit import check_settings
        if not self_labels:
            raise ValueError(f"the teacher's settings (--teacher-settings {teacher_settings}) "
                             "without self-labels: piles carry their own labels; valid: with "
                             "--self-labels, or own")
        check_settings(teacher_settings)
    if teacher_votes and seg.centre_net is None:
        raise ValueError(f"{model}: no centre-vote network to label with "
                         "(--teacher-centre-votes); valid: a model with centre votes "
                         "(`inseggan centres` makes one), or without the teacher's votes")


def piles_part(sim) -> str | None:
    """What the simulated piles `sim` are piles of, as the card says it: the simulator's own
    part (a library part: the true shape), or the learned template a model made
    (`simulate --object MODEL`) and, where it is not the model's rod, how it was made
    (`shape-fit --start discs`); None for a data set without a readable record."""
    from inseggan_ros.core import checkpoint
    from inseggan_ros.learning.piles import _model_file
    from inseggan_ros.sim.dataset import load_meta
    from inseggan_ros.sim.learned import is_model_path

    try:
        obj = str(load_meta(sim)["scene"]["object"])
    except (OSError, KeyError, ValueError):
        return None
    if not is_model_path(obj):
        return f"the simulator's {obj} (the true part)"
    try:
        state = checkpoint.load(_model_file(obj))
    except (ValueError, checkpoint.CheckpointError):  # gone since the piles were made
        return f"the learned template of `{obj}`"
    cfg, fit = state.get("model_config", {}), state.get("shape_fit")
    if cfg.get("renderer") == "spheres":
        return f"the learned rod of `{obj}`"
    if fit and fit["config"].get("start") == "discs":
        how = f"fitted {fit['iteration']} iterations" if fit["iteration"] else "not fitted"
        hole, taper = fit["config"].get("hole", 0.0), fit["config"].get("taper", 1.0)
        if fit.get("discs"):  # `shape-fit --match-piles`
            how = ("sized by simulated piles, " if hole or taper != 1 else
                   "the widest sized by simulated piles, ") + how
        if hole:  # `--pile-holes`
            return (f"the learned rod's profile as a hexagonal nut with a hole {hole:g} of its "
                    f"width (6 ring sectors), {how}, from `{obj}`")
        if taper != 1:  # `--pile-tapers`
            return (f"the learned rod's profile as a disc of {cfg.get('walls')} walls tapering "
                    f"to {taper:g} of its radius (a frustum), {how}, from `{obj}`")
        return (f"the learned rod's profile as {cfg.get('pieces')} flat-ended discs, {how}, "
                f"from `{obj}`")
    pieces = cfg.get("pieces")
    what = (f"{pieces} convex piece{'s' if pieces != 1 else ''} of {cfg.get('walls')} walls")
    if fit:  # `shape-fit` from a rod (`loop --convex-pieces`); the shipped block's record,
        # of an earlier format, names the kept iteration `kept`
        at = fit.get("iteration", fit.get("kept"))
        return (f"the learned rod fitted by reconstruction as {what} (best of "
                f"{fit['config']['iterations']} iterations, at {at}), from `{obj}`")
    return f"the learned template of `{obj}`, {what}"


def _self_labelled(model, seg, data, out: Path, frames: int | None, held_out: int,
                   workers: int, progress: bool, given: dict | None = None,
                   teacher_votes: bool = False, teacher_settings: str = "own") -> dict:
    """`fit`'s two splits from the user's data set's train split (or a recording's frames, all
    of them), labelled by the model (its own settings, or `teacher_settings`, and its tau;
    centre votes off unless `teacher_votes`; `selffit.self_labels`, in `workers` processes,
    resumable from out/self_labels.npz), the last `held_out` kept to choose by."""
    from inseggan_ros.io.bags import BagError
    from inseggan_ros.data.datasets import load_bag, load_sim_split
    from inseggan_ros.learning.selffit import SelfFitConfig, self_labels

    if held_out < 1:
        raise ValueError(f"held_out {held_out} invalid; valid: >= 1")
    if given is not None:
        train = {k: given[k][:frames] for k in ("x", "fg")}
    elif (Path(data) / "meta.json").is_file():  # a simulated data set: its train split
        train = load_sim_split(data, "train", seg.prep_cfg, limit=frames, progress=progress)
    else:  # a recording: every frame, cut as the model cuts a bag's
        try:
            train = load_bag(data, seg.prep_cfg, limit=frames, progress=progress)
        except BagError as e:
            raise ValueError(f"{data}: neither a simulated data set (no meta.json) nor a "
                             f"readable recording ({e}); valid: either") from None
    if len(train["x"]) <= held_out:
        raise ValueError(f"{data}: {len(train['x'])} training frames; valid: more than the "
                         f"{held_out} held out to choose the iteration by")
    labels = self_labels(model, train["x"], train["fg"], None, out / "self_labels.npz",
                         SelfFitConfig(settings=teacher_settings, workers=workers), progress,
                         overrides={"centre_votes": "on" if teacher_votes else "off"})
    k = len(labels) - held_out
    return {"train": {"x": train["x"][:k], "fg": train["fg"][:k], "labels": labels[:k]},
            "val": {"x": train["x"][k:], "fg": train["fg"][k:], "labels": labels[k:]}}
