"""A label head: the z-buffered labels corrected by a small network taught on simulated piles.

The encoder's poses, rendered and z-buffered, put each instance about where it is, but a pose
read in one pass is a few pixels off, and at 64 x 64 a few pixels are much of a part's outline:
the boundaries between touching instances are where the real-time labels lose to a classical
method that follows the depth's own edges. Test-time pose fitting fixes that at 20-50 times the
cost. The head instead looks, for every instance slot k, at the input, slot k's render, the
highest of the other renders and the pixels the z-buffer gave k, and scores each foreground pixel
for k (one small U-Net shared by all slots, so it is the same for any slot order and any number
of instances); each pixel takes the slot that scores highest. The score starts from the
z-buffer's own choice (a learned weight on slot k's mask), so the head learns a correction.

It is trained with the labels of scenes the simulator made of the learned part (`inseggan
loop`'s piles: no label of the user's frames), the slot of each true instance being the render
it overlaps most (Hungarian assignment on IoU), with cross-entropy on the foreground pixels and
the 8 symmetries of the square as augmentation. The pipeline stays encoder + per-instance
rendering + z-buffer; the head only moves pixels between instances the renders proposed.

    head = LabelHead()
    logits = head(x, renders, labels)      # (B, n, H, W)
    labels = head_labels(head, x, renders, labels, fg)
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment
from tqdm import tqdm

from inseggan_ros.evaluation.evaluate import write_json
from inseggan_ros.runtime.symmetry import SYMMETRIES, transform_image
from inseggan_ros.runtime.label_head import (  # noqa: F401  (the head, shared with inference)
    IN_CHANNELS, LabelHead, head_from_state, head_labels, head_state)


@dataclass(frozen=True)
class HeadConfig:
    width: int = 8  # channels at 64 x 64; 2x and 4x that at 32 x 32 and 16 x 16
    iterations: int = 2000
    batch: int = 32
    lr: float = 2e-3  # Adam, cosine schedule down to 0
    eval_every: int = 250
    seed: int = 0
    # The proposals it learns from are rendered anew each iteration from the encoder's poses
    # with the template's length and thickness each scaled by a random factor in
    # [1 / (1 + j), 1 + j] and each instance moved by up to `shift_jitter` pixels: on the user's
    # frames the learned template is not exactly the part, and the head must not count on it.
    scale_jitter: float = 0.0
    shift_jitter: float = 0.0

    def __post_init__(self):
        check_training(self)
        for key in ("scale_jitter", "shift_jitter"):
            if not getattr(self, key) >= 0:
                raise ValueError(f"{key} {getattr(self, key)!r} invalid; valid: >= 0")


def check_training(cfg) -> None:
    """Raises ValueError naming a bad count (width, iterations, batch, eval_every: >= 1) or
    learning rate (in (0, 1)) of a small network's training settings (`HeadConfig`,
    `centres.CentreConfig`)."""
    for key in ("width", "iterations", "batch", "eval_every"):
        if getattr(cfg, key) < 1:
            raise ValueError(f"{key} {getattr(cfg, key)!r} invalid; valid: >= 1")
    if not 0 < cfg.lr < 1:
        raise ValueError(f"lr {cfg.lr!r} invalid; valid: in (0, 1)")


def slot_targets(labels: np.ndarray, gt: np.ndarray, n: int) -> np.ndarray:
    """True instance ids -> slots: (B, H, W) z-buffer labels and ground truth (0 = background)
    -> (B, H, W) int64 targets, the slot (0..n-1) of each true instance's pixels, -1 on the
    background. Each true instance takes the slot whose labels overlap it most (IoU,
    Hungarian), so the head is taught to move pixels between the proposed instances, not to
    renumber them."""
    out = np.full(gt.shape, -1, np.int64)
    for b in range(len(gt)):
        ids = [i for i in np.unique(gt[b]) if i != 0]
        if not ids:
            continue
        g = gt[b][None] == np.asarray(ids)[:, None, None]  # (m, H, W)
        p = labels[b][None] == np.arange(1, n + 1)[:, None, None]  # (n, H, W)
        inter = (g[:, None] & p[None]).sum((-1, -2))
        union = (g[:, None] | p[None]).sum((-1, -2))
        rows, cols = linear_sum_assignment(-(inter / np.maximum(union, 1)))
        for r, c in zip(rows, cols):
            out[b][g[r]] = c
    return out


@torch.no_grad()
def proposals(segmenter, x: np.ndarray, fg: np.ndarray, batch: int = 100) -> tuple:
    """The segmenter's proposals with its settings (float32 encoder), before any head or
    smoothing: -> {"renders": (N, n, 64, 64), "labels": z-buffer (N, 64, 64) uint8, "pose":
    (N, n, 6) or None for templates without explicit poses}."""
    from inseggan_ros.runtime.model import TemplateGenerator
    from inseggan_ros.runtime.segment import infer, labels_from_renders

    cfg = segmenter.inference
    renders, labels, poses = [], [], []
    for i in range(0, len(x), batch):
        xb = torch.from_numpy(x[i:i + batch])
        out = infer(segmenter.G, segmenter.E, xb, refine_steps=cfg.refine_steps,
                    hypotheses=cfg.refine_hypotheses, keep=cfg.refine_keep,
                    swaps=cfg.refine_swaps)
        renders.append(out["renders"])
        labels.append(labels_from_renders(out["renders"], segmenter.tau,
                                          torch.from_numpy(fg[i:i + batch])))
        if "pose" in out:
            poses.append(out["pose"])
        elif isinstance(segmenter.G, TemplateGenerator):  # one start: the encoder's codes
            z = out["z"]
            poses.append(segmenter.G.pose(z.reshape(-1, z.shape[-1])).reshape(*z.shape[:2], 6))
    return {"renders": torch.cat(renders).numpy(), "labels": torch.cat(labels).numpy(),
            "pose": torch.cat(poses).numpy() if poses else None}


def _augment(x, r, lab, tgt, gen):
    """One random symmetry of the square for the whole batch (the head is not told which)."""
    sym = SYMMETRIES[int(torch.randint(0, len(SYMMETRIES), (1,), generator=gen))]
    return tuple(transform_image(t, sym) for t in (x, r, lab, tgt))


def miou_of(pred: np.ndarray, gt: np.ndarray) -> float:
    from inseggan_ros.core.metrics import mean_miou, miou_batch
    return float(mean_miou(miou_batch(pred, gt)))


@torch.no_grad()
def jittered_proposals(G, pose: torch.Tensor, fg: torch.Tensor, tau: float, cfg: HeadConfig,
                       gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, n, 6) poses -> renders and z-buffer labels of a template scaled at random and of
    instances moved at random (`HeadConfig.scale_jitter`, `shift_jitter`)."""
    from inseggan_ros.runtime.model import SphereGenerator
    from inseggan_ros.runtime.segment import labels_from_renders

    template = None
    if cfg.scale_jitter > 0:
        if not isinstance(G, SphereGenerator):
            raise ValueError(f"scale_jitter needs a rod template; the model's is "
                             f"{G.cfg.renderer} (scale_jitter: 0)")
        centres, radii = G.geometry()
        lo = math.log(1 + cfg.scale_jitter)
        s_len, s_rad = (torch.empty(2).uniform_(-lo, lo, generator=gen)).exp()
        template = (centres * s_len, radii * s_rad)
    if cfg.shift_jitter > 0:
        step = cfg.shift_jitter * 2 / fg.shape[-1]  # pixels -> template units
        shift = (torch.rand(*pose.shape[:2], 2, generator=gen) * 2 - 1) * step
        pose = pose.clone()
        pose[..., 3:5] += shift
    renders = G.render_poses(pose, fg.shape[-1], template=template)
    return renders, labels_from_renders(renders, tau, fg)


def train_head(G, tau: float, train: dict, val: dict | None, out,
               cfg: HeadConfig = HeadConfig(), progress: bool = True) -> dict:
    """Fit a `LabelHead` for the model whose generator is `G` (frozen) and threshold `tau`.

    `train` = {"x", "fg", "gt", "pose"}: labelled frames and the encoder's poses on them
    (`proposals`), rendered anew each iteration (`jittered_proposals`); `val` = {"x", "fg",
    "gt", "renders", "labels"}, scored every `eval_every` iterations by mIoU against its ground
    truth. Writes out/head.pt (the best on `val`, else the last) and out/summary.json. -> the
    summary."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    n = train["pose"].shape[1]
    head = LabelHead(cfg.width)
    opt = torch.optim.Adam(head.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda i: 0.5 * (1 + math.cos(math.pi * min(i, cfg.iterations) / cfg.iterations)))
    T = {k: torch.from_numpy(np.ascontiguousarray(train[k])) for k in ("x", "fg", "gt", "pose")}
    history, best, best_state, first_loss = [], -1.0, None, None
    t0 = time.monotonic()

    def score():
        head.eval()
        preds = [head_labels(head, *(torch.from_numpy(val[k][i:i + 100])
                                     for k in ("x", "renders", "labels", "fg"))).numpy()
                 for i in range(0, len(val["x"]), 100)]
        head.train()
        return miou_of(np.concatenate(preds), val["gt"])

    if val is not None:
        history.append({"iteration": 0, "val_miou_zbuffer": miou_of(val["labels"], val["gt"]),
                        "val_miou": score()})
    bar = tqdm(range(1, cfg.iterations + 1), desc="label head", unit="it", disable=not progress)
    loss_avg = None
    for it in bar:
        idx = torch.randint(0, len(T["x"]), (cfg.batch,), generator=gen)
        renders, labels = jittered_proposals(G, T["pose"][idx], T["fg"][idx], tau, cfg, gen)
        tgt = torch.from_numpy(slot_targets(labels.numpy(), T["gt"][idx].numpy(), n))
        x, r, lab, tgt = _augment(T["x"][idx], renders, labels.long(), tgt, gen)
        loss = F.cross_entropy(head(x, r, lab), tgt, ignore_index=-1)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        value = float(loss.detach())
        loss_avg = value if loss_avg is None else 0.95 * loss_avg + 0.05 * value
        first_loss = value if first_loss is None else first_loss
        bar.set_postfix(loss=f"{loss_avg:.3f}")
        if val is not None and (it % cfg.eval_every == 0 or it == cfg.iterations):
            m = score()
            history.append({"iteration": it, "loss": loss_avg, "val_miou": m})
            if m > best:
                best, best_state = m, {k: v.clone() for k, v in head.state_dict().items()}
            bar.write(f"iteration {it}: loss {loss_avg:.4f}, validation mIoU {m:.4f}")
    bar.close()
    if best_state is not None:
        head.load_state_dict(best_state)
    save_head(head, out / "head.pt")
    summary = {"config": asdict(cfg), "seconds": round(time.monotonic() - t0, 1),
               "history": history, "best_val_miou": best if val is not None else None,
               "first_loss": first_loss, "last_loss": loss_avg,
               "train_frames": int(len(T["x"]))}
    write_json(out / "summary.json", summary)
    return summary


def save_head(head: LabelHead, path) -> Path:
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(head_state(head), tmp)
    tmp.replace(path)
    return path


def fit(model, sim, out, cfg: HeadConfig = HeadConfig(), tau: float | None = None,
        frames: int | None = None, progress: bool = True, as_given: bool = False) -> dict:
    """A label head for `model` (a checkpoint) from the labelled scenes of the simulated data
    set `sim` (its train split to learn from, its val split to choose the best iteration):
    out/head.pt, out/summary.json, and out/model.pt, the model with the head and its settings
    switched to it (`label_head: on`) at the tau it was trained for (`tau`, default the
    model's: the z-buffer labels the head corrects depend on it). `as_given`: the scenes are
    cut as the model's preprocessing says, the bin found in every frame where it names none
    (`data.load_sim_split`; a model learned from a bag). Resumes nothing: a run takes minutes.
    -> the summary, with "model"."""
    from dataclasses import replace

    from inseggan_ros.core import checkpoint
    from inseggan_ros.data.datasets import load_sim_split
    from inseggan_ros.runtime.segment import Segmenter
    from inseggan_ros.core.settings import InferenceConfig

    out = Path(out)
    state = checkpoint.load(model)
    seg = Segmenter.from_checkpoint(model, device="cpu", tau=tau)
    seg.inference = replace(seg.inference, label_head="off",  # proposals: the z-buffer's
                            centre_votes="off")
    splits = {}
    for split in ("train", "val"):
        d = load_sim_split(sim, split, seg.prep_cfg, limit=frames, progress=progress,
                           as_given=as_given)
        if len(d["x"]) == 0:
            raise ValueError(f"{sim}: no scenes in its {split} split; valid: a simulated data "
                             "set with train and val scenes (`inseggan simulate`, the loop's "
                             "out/sim)")
        splits[split] = {"x": d["x"], "fg": d["fg"], "gt": d["labels"],
                         **proposals(seg, d["x"], d["fg"])}
    if splits["train"]["pose"] is None:
        raise ValueError(f"{model}: the label head learns from rendered poses; the "
                         f"{seg.model_cfg.renderer} renderer has none")
    summary = train_head(seg.G, seg.tau, splits["train"], splits["val"], out, cfg, progress)
    head = head_from_state(torch.load(out / "head.pt", weights_only=True))
    inference = replace(InferenceConfig.from_dict(state.get("inference", {})), label_head="on",
                        centre_votes="off")  # the head's labels instead of the votes
    keep = {k: v for k, v in state.items() if k not in ("format", "optimizers", "rng")}
    keep.update(tau=seg.tau, label_head={**head_state(head), "tau": seg.tau,
                                         "sim": str(sim), "summary": summary},
                inference=inference.to_dict())
    checkpoint.save(out / "model.pt", keep)
    return {**summary, "model": str(out / "model.pt"), "tau": seg.tau}
