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
import torch.nn as nn
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment
from tqdm import tqdm

from .evaluate import write_json
from .symmetry import SYMMETRIES, transform_image

OFFSET_UNIT = 8.0  # offsets are predicted in units of 8 pixels (about a part's half-length)
HEAT_SIGMA = 2.0  # pixels: the Gaussian round each centre in the heatmap's target
PEAK_THRESHOLD = 0.3  # a heatmap peak below this is no instance (the highest always is one)
PEAK_RADIUS = 3  # pixels: a peak is the highest point within this distance
MIN_PIXELS = 4  # a true instance with fewer visible pixels has no centre in the target


@dataclass(frozen=True)
class CentreConfig:
    width: int = 16  # channels at 64 x 64; 2x and 4x that at 32 x 32 and 16 x 16
    iterations: int = 3000
    batch: int = 32
    lr: float = 2e-3  # Adam, one-cycle schedule (a short warm-up, then cosine down)
    eval_every: int = 500
    seed: int = 0

    def __post_init__(self):
        from .label_head import check_training
        check_training(self)
        if self.iterations < 4:  # fewer leave the one-cycle schedule a phase of no steps
            raise ValueError(f"iterations {self.iterations!r} invalid; valid: >= 4 (a warm-up "
                             "and a decay)")


def _block(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1), nn.GroupNorm(4, cout),
                         nn.LeakyReLU(0.2))


class CentreNet(nn.Module):
    """(B, 2, 64, 64) heights and foreground -> (B, 3, 64, 64): the centre heatmap's logit and
    the offset (dy, dx) from each pixel to its part's centre, in OFFSET_UNIT pixels. A U-Net
    with three levels (64, 32, 16 pixels)."""

    def __init__(self, width: int = 16):
        super().__init__()
        w = self.width = width
        self.e1 = nn.Sequential(_block(2, w), _block(w, w))
        self.e2 = nn.Sequential(_block(w, 2 * w, 2), _block(2 * w, 2 * w))
        self.e3 = nn.Sequential(_block(2 * w, 4 * w, 2), _block(4 * w, 4 * w),
                                _block(4 * w, 4 * w))
        self.d2 = nn.Sequential(_block(6 * w, 2 * w), _block(2 * w, 2 * w))
        self.d1 = nn.Sequential(_block(3 * w, w), _block(w, w))
        self.out = nn.Conv2d(w, 3, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a = self.e1(x)
        b = self.e2(a)
        c = self.e3(b)
        b = self.d2(torch.cat([_up2(c), b], 1))
        a = self.d1(torch.cat([_up2(b), a], 1))
        return self.out(a.to(self.out.weight.dtype))  # a float32 last layer: `CastCentreNet`


def _up2(x: torch.Tensor) -> torch.Tensor:
    """Nearest-neighbour upsampling by 2: F.interpolate's values, at a third of its time on
    one CPU thread at these sizes."""
    return x.repeat_interleave(2, -2).repeat_interleave(2, -1)


def net_input(x, fg) -> torch.Tensor:
    """(B, 1, H, W) model input and (B, H, W) foreground -> (B, 2, H, W)."""
    x = torch.as_tensor(x, dtype=torch.float32)
    fg = torch.as_tensor(fg).to(torch.float32)
    return torch.cat([x, fg[:, None]], 1)


def _grid(H: int, W: int) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.arange(H, dtype=torch.float32).view(H, 1).expand(H, W),
            torch.arange(W, dtype=torch.float32).view(1, W).expand(H, W))


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


@torch.no_grad()
def decode(pred: torch.Tensor, fg, n: int) -> torch.Tensor:
    """(B, 3, H, W) net output and (B, H, W) foreground -> (B, H, W) uint8 labels: the
    heatmap's peaks (at most n, each the highest within PEAK_RADIUS, above PEAK_THRESHOLD; the
    highest always counts), labelled 1.. in order of height, and every foreground pixel given
    the peak nearest where its offset points. A peak may lie off the foreground: the centre of
    a part with a hole (a nut lying flat) is in the hole (peaks on the foreground only cost a
    net taught on the nut's frames 0.918 -> 0.648 on its validation split; the cylinder's and
    the bolt's labels are the same either way: docs/experiments.md, 2026-11-29)."""
    pred = pred.float()
    fg = torch.as_tensor(fg, dtype=torch.bool, device=pred.device)
    B, _, H, W = pred.shape
    heat = torch.sigmoid(pred[:, 0])
    k, r = 2 * PEAK_RADIUS + 1, PEAK_RADIUS  # the square's max as a row's then a column's
    local = F.max_pool2d(F.max_pool2d(heat[:, None], (1, k), 1, (0, r)), (k, 1), 1, (r, 0))[:, 0]
    score = torch.where(heat == local, heat, torch.zeros_like(heat)).flatten(1)
    top = score.topk(min(n, H * W), dim=1)
    keep = top.values > PEAK_THRESHOLD
    keep[:, 0] = True
    ys, xs = _grid(H, W)
    cy, cx = ys.flatten()[top.indices], xs.flatten()[top.indices]  # (B, k)
    vy = ys + pred[:, 1] * OFFSET_UNIT  # where each pixel's vote lands
    vx = xs + pred[:, 2] * OFFSET_UNIT
    d = (vy[:, None] - cy[..., None, None]) ** 2 + (vx[:, None] - cx[..., None, None]) ** 2
    d = torch.where(keep[..., None, None], d, torch.full_like(d, float("inf")))
    labels = (d.min(1).indices + 1).to(torch.uint8)  # argmin's, at a twentieth of its time
    labels[~fg] = 0
    return labels


@torch.no_grad()
def centre_labels(net: CentreNet, x, fg, n: int) -> torch.Tensor:
    """(B, 1, H, W) model inputs and (B, H, W) foreground -> (B, H, W) uint8 labels."""
    return decode(net(net_input(x, fg)), fg, n)


def match_to_renders(labels: torch.Tensor, zbuffer: torch.Tensor, n: int) -> torch.Tensor:
    """Centre-vote labels renumbered so that each takes the id of the z-buffer label it overlaps
    most (Hungarian assignment on the overlap, frame by frame): an instance's id then names the
    render nearest it, whose pose, score and pick the node reports."""
    lab, zb = labels.cpu().numpy(), zbuffer.cpu().numpy()
    out = np.zeros_like(lab)
    for b in range(len(lab)):
        overlap = np.zeros((n + 1, n + 1), np.int64)
        np.add.at(overlap, (lab[b].ravel(), zb[b].ravel()), 1)
        rows, cols = linear_sum_assignment(-overlap[1:, 1:])
        mapping = np.zeros(n + 1, lab.dtype)
        mapping[rows + 1] = cols + 1
        out[b] = mapping[lab[b]]
    return torch.from_numpy(out).to(labels.device)


def net_state(net: CentreNet) -> dict:
    """What a checkpoint stores of the net (its "centre_net" entry)."""
    from .checkpoint import width_state
    return width_state(net)


def net_from_state(state: dict) -> CentreNet:
    from .checkpoint import from_width_state
    return from_width_state(CentreNet, state)


def miou_of(pred: np.ndarray, gt: np.ndarray) -> float:
    from .metrics import mean_miou, miou_batch
    return float(mean_miou(miou_batch(pred, gt)))


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
    from .viz import plot_history

    plot_history(history, path, [("losses (training)", "train", ("heat", "offset")),
                                 ("piles' validation mIoU", "val", ("val_miou",))])


def fit(model, sim, out, cfg: CentreConfig = CentreConfig(), frames: int | None = None,
        progress: bool = True, as_given: bool = False, self_labels: bool = False,
        held_out: int = 200, workers: int = 1, user_frames: dict | None = None,
        teacher_votes: bool = False, teacher_settings: str = "own") -> dict:
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
    held-out cut)."""
    from dataclasses import replace

    from . import checkpoint
    from .data import load_sim_split
    from .segment import Segmenter
    from .settings import InferenceConfig

    out = Path(out)
    state = checkpoint.load(model)
    seg = Segmenter.from_checkpoint(model, device="cpu")
    n = seg.model_cfg.n_instances
    if teacher_votes and not self_labels:
        raise ValueError("the teacher's centre votes (--teacher-centre-votes) without "
                         "self-labels: piles carry their own labels; valid: with "
                         "--self-labels, or without the teacher's votes")
    if teacher_settings != "own":
        from .selffit import check_settings
        if not self_labels:
            raise ValueError(f"the teacher's settings (--teacher-settings {teacher_settings}) "
                             "without self-labels: piles carry their own labels; valid: with "
                             "--self-labels, or own")
        check_settings(teacher_settings)
    if teacher_votes and seg.centre_net is None:
        raise ValueError(f"{model}: no centre-vote network to label with "
                         "(--teacher-centre-votes); valid: a model with centre votes "
                         "(`inseggan centres` makes one), or without the teacher's votes")
    if self_labels:
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
    keep.update(centre_net={**net_state(net), "sim": str(sim),
                            "piles_part": None if self_labels else piles_part(sim),
                            "teacher": ("self-labels" if self_labels else "piles")
                            + (" with its centre votes" if teacher_votes else ""),
                            "teacher_settings": teacher_settings if self_labels else None,
                            "summary": {k: v for k, v in summary.items() if k != "history"}},
                inference=inference.to_dict())
    checkpoint.save(out / "model.pt", keep)
    return {**summary, "model": str(out / "model.pt")}


def piles_part(sim) -> str | None:
    """What the simulated piles `sim` are piles of, as the card says it: the simulator's own
    part (a library part: the true shape), or the learned template a model made
    (`simulate --object MODEL`) and, where it is not the model's rod, how it was made
    (`shape-fit --start discs`); None for a data set without a readable record."""
    from . import checkpoint
    from .loop import _model_file
    from .sim.dataset import load_meta
    from .sim.learned import is_model_path

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
    if fit:  # `shape-fit` from a rod (`loop --convex-pieces`)
        return (f"the learned rod fitted by reconstruction as {what} (best of "
                f"{fit['config']['iterations']} iterations, at {fit['iteration']}), from `{obj}`")
    return f"the learned template of `{obj}`, {what}"


def _self_labelled(model, seg, data, out: Path, frames: int | None, held_out: int,
                   workers: int, progress: bool, given: dict | None = None,
                   teacher_votes: bool = False, teacher_settings: str = "own") -> dict:
    """`fit`'s two splits from the user's data set's train split (or a recording's frames, all
    of them), labelled by the model (its own settings, or `teacher_settings`, and its tau;
    centre votes off unless `teacher_votes`; `selffit.self_labels`, in `workers` processes,
    resumable from out/self_labels.npz), the last `held_out` kept to choose by."""
    from .bags import BagError
    from .data import load_bag, load_sim_split
    from .selffit import SelfFitConfig, self_labels

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
