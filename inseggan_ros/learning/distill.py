"""Distilling test-time refinement into the encoder (amortised inference).

The encoder's poses are only a starting point: Levenberg-Marquardt refinement (`segment.
refine_poses`) improves them a lot, at a price of up to half a second a frame. Distillation
makes the start itself better, so that a real-time setting (few or no refinement iterations)
gains most of that:

  1. pseudo-labels: the refined poses of `frames` unlabelled training frames (the model's own
     best fit; no ground truth is used), written in chunks to pseudo.pt, so a killed run resumes;
  2. the encoder is fine-tuned to predict them directly (G frozen): Hungarian-matched pose
     features (translation, and the axis up to sign: what a render depends on) plus the
     real-frame reconstruction loss, each frame randomly mirrored or transposed with its poses.

    inseggan distill --checkpoint runs/cylinder_s1/best.pt --data data/cylinder \
        --out runs/cylinder_distill

With `--encoder-nf N` step 2 trains an encoder of width N instead (faster at test time),
started from the source's by channel pruning (`narrowed`); `--lr-schedule cosine` lowers the
learning rate to 0 at the last iteration.

Writes last.pt (every `eval_every` iterations; `--resume` continues from it) and best.pt (best
validation score, as `inseggan train`: mIoU of the encoder's own poses where the validation
frames have labels): training checkpoints with the new encoder, which `inseggan export` ships.
Also log.jsonl, curves.png and summary.json. Explicit-template models only (SphereGenerator).
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from inseggan_ros.core import checkpoint
from inseggan_ros.learning import losses
from inseggan_ros.evaluation.evaluate import write_json
from inseggan_ros.runtime.model import Encoder, ModelConfig, SphereGenerator, pose_features
from inseggan_ros.runtime.refine import refine_poses, start_poses
from inseggan_ros.runtime.symmetry import SYMMETRIES, transform_image, transform_poses
from inseggan_ros.runtime.model import build_models


@dataclass(frozen=True)
class DistillConfig:
    frames: int = 4000  # training frames given pseudo-labels
    refine_steps: int = 24  # pseudo-labels: Levenberg-Marquardt iterations ...
    hypotheses: int = 8  # ... from this many starting points
    chunk: int = 100  # frames refined (and saved) at a time
    iterations: int = 6000
    batch_size: int = 32
    lr: float = 3e-4
    lr_schedule: str = "constant"  # or "cosine": from lr down to 0 at the last iteration
    lambda_real: float = 1.0  # weight of the real-frame reconstruction loss
    recon_levels: int = 4
    eval_every: int = 500
    eval_frames: int = 100
    seed: int = 0
    encoder_nf: int = 0  # 0: fine-tune the source's encoder; else one this wide, pruned
    # from it (narrower) or widened from it (`widened`)
    lambda_pose: float = 1.0  # weight of the pseudo-label pose loss (0: no pseudo-labels made)
    lambda_label: float = 0.0  # weight of the ground-truth label loss (`losses.label_loss`):
    # simulated scenes of the part, whose labels are known
    lambda_ownership: float = 0.0  # weight of `losses.ownership_loss` (needs the labels too)
    lambda_user: float = 0.0  # weight of the reconstruction loss on a second batch, of the
    # user's own unlabelled frames (`user_x`): keeps an encoder fitted to simulated scenes
    # explaining the frames it will see
    labels: str = "simulated"  # where `train_labels` come from, for the card: "simulated"
    # (known labels of simulated piles, `loop`) or "self" (the model's own labels of the
    # user's frames, `selffit`)

    def __post_init__(self):
        for name in ("frames", "refine_steps", "hypotheses", "chunk", "iterations", "batch_size",
                     "eval_every", "eval_frames", "recon_levels"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} {getattr(self, name)!r} invalid; valid: >= 1")
        if not self.lr > 0 or not self.lambda_real >= 0:
            raise ValueError(f"lr {self.lr!r} must be > 0 and lambda_real {self.lambda_real!r} "
                             ">= 0")
        if self.lambda_ownership < 0 or (self.lambda_ownership > 0 and self.lambda_label <= 0):
            raise ValueError(f"lambda_ownership {self.lambda_ownership!r} invalid; valid: >= 0, "
                             "and > 0 only with lambda_label > 0 (both use the labels)")
        if not (self.lambda_pose >= 0 and self.lambda_label >= 0
                and self.lambda_pose + self.lambda_label > 0):
            raise ValueError(f"lambda_pose {self.lambda_pose!r} and lambda_label "
                             f"{self.lambda_label!r} invalid; valid: both >= 0, not both 0")

        if not self.lambda_user >= 0:
            raise ValueError(f"lambda_user {self.lambda_user!r} invalid; valid: >= 0")
        if self.labels not in ("simulated", "self"):
            raise ValueError(f"labels {self.labels!r} invalid; valid: simulated, self")
        if self.lr_schedule not in ("constant", "cosine"):
            raise ValueError(f"lr_schedule {self.lr_schedule!r} invalid; valid: constant, cosine")
        if self.encoder_nf != 0 and (self.encoder_nf < 8 or self.encoder_nf % 8):
            raise ValueError(f"encoder_nf {self.encoder_nf!r} invalid; valid: 0 (fine-tune the "
                             "source's encoder) or a multiple of 8, >= 8")


def pseudo_labels(G, E, x: np.ndarray, cfg: DistillConfig, path: Path,
                  progress: bool = True) -> torch.Tensor:
    """(N, 1, 64, 64) frames -> (N, n, 6) refined poses, computed `chunk` frames at a time and
    saved to `path` after each chunk (atomically); what is there already is reused."""
    done = torch.empty(0)
    settings = {"refine_steps": cfg.refine_steps, "hypotheses": cfg.hypotheses}
    if path.is_file():
        saved = torch.load(path, weights_only=False)
        if saved["settings"] == settings:
            done = saved["poses"]
    bar = tqdm(total=len(x), initial=len(done), desc="pseudo-labels", unit="frame",
               disable=not progress, dynamic_ncols=True)
    parts = [done] if len(done) else []
    with torch.no_grad():
        for i in range(len(done), len(x), cfg.chunk):
            xb = torch.from_numpy(x[i:i + cfg.chunk])
            parts.append(refine_poses(G, start_poses(G, E, xb, cfg.hypotheses), xb,
                                      cfg.refine_steps))
            checkpoint.save(path, {"settings": settings, "poses": torch.cat(parts)})  # atomic
            bar.update(len(xb))
    bar.close()
    return torch.cat(parts)[:len(x)]


def _symmetry_batch(x: torch.Tensor, pose: torch.Tensor | None, gen: torch.Generator,
                    labels: torch.Tensor | None = None):
    """Each frame under a random one of the 8 symmetries of the square (mirrored and/or
    transposed: `symmetry.SYMMETRIES`), its poses and labels (where given) with it."""
    pick = torch.randint(0, len(SYMMETRIES), (len(x),), generator=gen)
    x = x.clone()
    pose = pose.clone() if pose is not None else None
    labels = labels.clone() if labels is not None else None
    for k, sym in enumerate(SYMMETRIES[1:], 1):
        sel = pick == k
        if sel.any():
            x[sel] = transform_image(x[sel], sym)
            if pose is not None:
                pose[sel] = transform_poses(pose[sel], sym)
            if labels is not None:
                labels[sel] = transform_image(labels[sel], sym)
    return x, pose, labels


def narrowed(E: Encoder, nf: int) -> Encoder:
    """A copy of encoder E with width `nf` (`ModelConfig.encoder_nf`), a starting point for
    distillation (channel pruning): of each convolution's output channels it keeps those that
    carry most downstream, |instance-norm scale| x the L1 norm of the next convolution's weights
    on the channel, with their weights."""
    cfg = E.cfg
    new = Encoder(ModelConfig(**{**asdict(cfg), "encoder_nf": nf}))
    layers = list(E.derender) + list(E.head)
    new_layers = list(new.derender) + list(new.head)
    convs = [i for i, m in enumerate(layers) if isinstance(m, torch.nn.Conv2d)]
    with torch.no_grad():
        keep_in = torch.arange(layers[convs[0]].in_channels)  # the image (and coordinates)
        for k, i in enumerate(convs):
            conv, out = layers[i], new_layers[i]
            after = layers[i + 1] if i + 1 < len(layers) else None
            norm = after if isinstance(after, torch.nn.InstanceNorm2d) else None
            if k + 1 < len(convs):
                score = layers[convs[k + 1]].weight.abs().sum((0, 2, 3))
                if norm is not None:
                    score = score * norm.weight.abs()
                keep = score.argsort(descending=True)[:out.out_channels].sort().values
            else:
                keep = torch.arange(conv.out_channels)  # the codes
            out.weight.copy_(conv.weight[keep][:, keep_in])
            out.bias.copy_(conv.bias[keep])
            if norm is not None:
                new_layers[i + 1].weight.copy_(norm.weight[keep])
                new_layers[i + 1].bias.copy_(norm.bias[keep])
            keep_in = keep
    return new


def widened(E: Encoder, nf: int, noise: float = 1e-2, seed: int = 0) -> Encoder:
    """A copy of encoder E with the larger width `nf` that computes what E computes (Net2Net's
    widening, Chen et al. 2016): each convolution's new output channels copy old ones (with
    their instance-norm scale and shift, so a copy is normalised exactly as its original), and
    the next convolution's weights on a channel and its copies are the original's divided among
    them. `noise` (relative to each weight tensor's std) on those divided weights breaks the
    copies' symmetry, which gradients alone would never break."""
    if nf < E.width:
        raise ValueError(f"encoder_nf {nf} is narrower than the encoder's {E.width}: `narrowed`")
    new = Encoder(ModelConfig(**{**asdict(E.cfg), "encoder_nf": nf}))
    layers = list(E.derender) + list(E.head)
    new_layers = list(new.derender) + list(new.head)
    convs = [i for i, m in enumerate(layers) if isinstance(m, torch.nn.Conv2d)]
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        src_in = torch.arange(layers[convs[0]].in_channels)  # the image (and coordinates)
        for i in convs:
            conv, out = layers[i], new_layers[i]
            # each new output channel's original: the old ones, then copies of them in turn
            src = torch.arange(out.out_channels) % conv.out_channels
            copies = torch.bincount(src_in, minlength=conv.in_channels)[src_in].float()
            w = conv.weight[src][:, src_in] / copies[None, :, None, None]
            shared = (copies > 1)[None, :, None, None]  # weights on an input that was copied
            w = w + shared * torch.randn(w.shape, generator=gen) * noise * conv.weight.std()
            out.weight.copy_(w)
            out.bias.copy_(conv.bias[src])
            after = layers[i + 1] if i + 1 < len(layers) else None
            if isinstance(after, torch.nn.InstanceNorm2d):
                new_layers[i + 1].weight.copy_(after.weight[src])
                new_layers[i + 1].bias.copy_(after.bias[src])
            src_in = src
    return new


# Heights outside [SUNK, RAISED] (image half-widths) all render the same: below, the rod is out
# of sight; above, its whole footprint saturates at max_height. The fit drifts there without
# bound (cylinder pseudo-labels reached +164, 224 of 20,000 instances above 2), which gave the
# pose loss spikes of up to 18; targets and predictions are compared with heights clamped.
SUNK, RAISED = -1.0, 1.5


def _features(pose: torch.Tensor) -> torch.Tensor:
    """(B, n, 6) poses -> (B, n, 9) what a render depends on (`model.pose_features`), the
    height clamped to [SUNK, RAISED]."""
    from inseggan_ros.runtime.model import pose_matrix

    B, n, _ = pose.shape
    pose = torch.cat([pose[..., :5], pose[..., 5:].clamp(SUNK, RAISED)], -1)
    return pose_features(pose_matrix(pose.reshape(B * n, 6))).reshape(B, n, -1)


@torch.no_grad()
def evaluate(G, E, val: dict, tau: float) -> dict:
    """The encoder's own poses (no refinement) on validation frames: reconstruction error and,
    where there are labels, mIoU at the model's tau (on the models' device)."""
    from inseggan_ros.core.metrics import mean_miou, miou_batch
    from inseggan_ros.runtime.segment import labels_from_renders

    E.eval()
    device = next(E.parameters()).device
    x = torch.from_numpy(val["x"]).to(device)
    pose = torch.cat([start_poses(G, E, x[i:i + 100])[:, 0] for i in range(0, len(x), 100)])
    renders = G.render_poses(pose)
    out = {"recon_l1": float((G.zbuffer(renders) - x).abs().mean())}
    if val.get("labels") is not None:
        fg = torch.from_numpy(val["fg"]).to(device)
        out["miou"] = float(mean_miou(miou_batch(
            labels_from_renders(renders, tau, fg).cpu().numpy(), val["labels"])))
    E.train()
    return out


def plot_curves(history: list, path: Path) -> None:
    from inseggan_ros.core.viz import plot_history

    plot_history(history, path, [("distillation losses", "train",
                                  ("l_pose", "l_label", "l_real", "l_user")),
                                 ("validation, no refinement", "val", ("miou", "recon_l1"))])


@dataclass
class _Distillation:
    """What the phases of one distillation share: the frozen generator, the encoder trained, its
    optimiser, the generator of the batches' draws and symmetries, and the record so far."""

    cfg: DistillConfig
    source: object
    state: dict  # the source checkpoint's, with the new encoder's width
    previous: dict | None  # the source's own distillation record
    self_fit: dict | None
    G: torch.nn.Module
    E: torch.nn.Module
    opt: torch.optim.Optimizer
    gen: torch.Generator
    out: Path
    val: dict | None
    tau: float
    it: int = 0
    best: float = -math.inf
    history: list = field(default_factory=list)
    before: float = 0.0  # seconds of the run before this process (a resumed run)
    start: float = 0.0  # time.monotonic() when this process began training

    def seconds(self) -> float:
        return self.before + time.monotonic() - self.start

    def resume(self) -> None:
        """Continue from out/last.pt: the encoder, optimiser, generator and record."""
        saved = checkpoint.load(self.out / "last.pt")
        last = saved["distill"]
        self.E.load_state_dict(saved["encoder"])
        self.opt.load_state_dict(last["optimizer"])
        self.gen.set_state(last["generator"])
        self.it, self.best, self.history, self.before = (last["iteration"], last["best"],
                                                         last["history"], last["seconds"])

    def save(self, path: Path) -> None:
        record = {"config": asdict(self.cfg), "source": str(self.source), "iteration": self.it,
                  "best": self.best, "previous": self.previous, "self_fit": self.self_fit,
                  "history": self.history, "seconds": self.seconds(),
                  "optimizer": self.opt.state_dict(), "generator": self.gen.get_state()}
        checkpoint.save(path, {**{k: v for k, v in self.state.items()
                                  if k not in ("format", "distill_record")},
                               "encoder": {k: v.cpu() for k, v in self.E.state_dict().items()},
                               "distill": record})

    def log(self, rec: dict) -> None:
        self.history.append(rec)
        with open(self.out / "log.jsonl", "a") as f:
            f.write(json.dumps(rec) + "\n")

    def validate(self) -> bool:
        """Logs the validation record; -> whether its score is the best yet."""
        v = evaluate(self.G, self.E, self.val, self.tau)
        score = v.get("miou", -v["recon_l1"])
        improved = score > self.best
        self.best = max(self.best, score)
        self.log({"kind": "val", "iteration": self.it, **v})
        plot_curves(self.history, self.out / "curves.png")
        tqdm.write(f"iter {self.it}: " + ", ".join(f"{k} {v_:.4f}" for k, v_ in v.items())
                   + (" (best)" if improved else ""))
        return improved


def _source_models(source, cfg: DistillConfig, train_labels, user_x):
    """The source checkpoint -> (its state, its own distillation record, G, E), refused where
    `cfg` asks for what it or the given data cannot supply."""
    from inseggan_ros.evaluation.modelcard import distill_record

    state = checkpoint.load(source)
    previous = distill_record(state)
    card = Path(source).parent / "card.json"
    if previous is None and Path(source).name == "model.pt" and card.is_file():
        previous = json.loads(card.read_text()).get("distillation")  # exported before the
        # model kept its record
    _, G, E = build_models(state, source)
    if cfg.lambda_pose > 0 and not isinstance(G, SphereGenerator):
        raise ValueError(f"{source}: distillation needs a rod template (renderer 'spheres': "
                         f"the pose fit it distils is the rod's), not {G.cfg.renderer!r}; "
                         "label supervision alone (lambda_pose 0) works with any template")
    if cfg.lambda_label > 0 and train_labels is None:
        raise ValueError("lambda_label > 0 needs the training frames' labels (a simulated data "
                         "set); none were given")
    if cfg.lambda_user > 0 and (user_x is None or not len(user_x)):
        raise ValueError("lambda_user > 0 needs the user's frames (user_x); none were given")
    return state, previous, G, E


def _losses(run: _Distillation, xb, target, lb, ut, device):
    """One batch's (l_pose, l_label, l_real, l_user); the user's batch drawn from `ut`."""
    cfg, G, E = run.cfg, run.G, run.E
    z = E(xb)
    B, n, d = z.shape
    pose = G.pose(z.reshape(B * n, d)).reshape(B, n, 6)
    renders = G.render_poses(pose)
    l_pose = (losses.alignment_loss(_features(target), _features(pose)) if target is not None
              else renders.new_zeros(()))
    l_label = (losses.label_loss(renders, lb, xb) if lb is not None
               else renders.new_zeros(()))
    if lb is not None and cfg.lambda_ownership > 0:
        l_label = l_label + cfg.lambda_ownership / max(cfg.lambda_label, 1e-9) * \
            losses.ownership_loss(renders, lb)
    l_real = losses.pyramid_l1(G.zbuffer(renders), xb, cfg.recon_levels)
    l_user = renders.new_zeros(())
    if ut is not None:  # the user's frames: nothing known but the frame itself
        ub = _symmetry_batch(ut[torch.randint(0, len(ut), (cfg.batch_size,), generator=run.gen)],
                             None, run.gen)[0].to(device)
        zu = E(ub)
        upose = G.pose(zu.reshape(B * n, d)).reshape(B, n, 6)
        l_user = losses.pyramid_l1(G.zbuffer(G.render_poses(upose)), ub, cfg.recon_levels)
    return l_pose, l_label, l_real, l_user


def _step(run: _Distillation, xt, pseudo, lab, ut, device) -> dict:
    """One iteration: a batch under random symmetries, its losses, an Adam step -> its losses."""
    cfg, opt, gen = run.cfg, run.opt, run.gen
    idx = torch.randint(0, len(xt), (cfg.batch_size,), generator=gen)
    xb, target, lb = (t.to(device) if t is not None else None for t in _symmetry_batch(
        xt[idx], pseudo[idx] if pseudo is not None else None, gen,
        lab[idx] if lab is not None else None))
    l_pose, l_label, l_real, l_user = _losses(run, xb, target, lb, ut, device)
    opt.zero_grad(set_to_none=True)
    (cfg.lambda_pose * l_pose + cfg.lambda_label * l_label
     + cfg.lambda_real * l_real + cfg.lambda_user * l_user).backward()
    if cfg.lr_schedule == "cosine":  # a function of the iteration: a resumed run follows it
        for group in opt.param_groups:
            group["lr"] = cfg.lr * 0.5 * (1 + math.cos(math.pi * run.it / cfg.iterations))
    opt.step()
    run.it += 1
    return {"l_pose": round(l_pose.item(), 5), "l_label": round(l_label.item(), 5),
            "l_real": round(l_real.item(), 5), "l_user": round(l_user.item(), 5)}


def _train_encoder(run: _Distillation, xt, pseudo, lab, ut, device, progress: bool) -> dict:
    """Iterations up to `cfg.iterations`, logged, validated and saved -> the last losses."""
    cfg, out = run.cfg, run.out
    bar = tqdm(total=cfg.iterations, initial=run.it, desc="distilling", unit="it",
               disable=not progress, dynamic_ncols=True)
    stats = {}
    while run.it < cfg.iterations:
        stats = _step(run, xt, pseudo, lab, ut, device)
        bar.update(1)
        bar.set_postfix(pose=f"{stats['l_pose']:.3f}", label=f"{stats['l_label']:.3f}",
                        real=f"{stats['l_real']:.3f}", user=f"{stats['l_user']:.3f}")
        if run.it % 50 == 0:
            run.log({"kind": "train", "iteration": run.it, **stats})
        if run.it % cfg.eval_every == 0 or run.it == cfg.iterations:
            if run.val is not None and run.validate():
                run.save(out / "best.pt")
            run.save(out / "last.pt")
    bar.close()
    return stats


def distill(source, train_x: np.ndarray, val: dict | None, out,
            cfg: DistillConfig = DistillConfig(),
            resume: bool = False, progress: bool = True,
            train_labels: np.ndarray | None = None,
            user_x: np.ndarray | None = None, device: str = "cpu",
            self_fit: dict | None = None) -> dict:
    """Fine-tune the encoder of training checkpoint `source` on `train_x` ((N, 1, 64, 64)
    prepared frames; the first `cfg.frames` are used) and, with `cfg.lambda_label` > 0, their
    ground-truth `train_labels` ((N, 64, 64): simulated scenes of the part); with
    `cfg.lambda_user` > 0, also to reconstruct `user_x` ((M, 1, 64, 64) unlabelled frames of
    the user's camera). `device`: where the encoder trains ("auto": a GPU when there is one; the
    pseudo-labels are refined on the CPU). `self_fit`: how the labels were made when they are
    the model's own (`selffit`), for the card. The source's own distillation, if any, is kept in
    the new record as "previous". -> summary (also out/summary.json)."""
    state, previous, G, E = _source_models(source, cfg, train_labels, user_x)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    G.eval()
    for p in G.parameters():
        p.requires_grad_(False)
    tau = float(state.get("tau", -0.5))
    x = np.ascontiguousarray(train_x[:cfg.frames], dtype=np.float32)
    # 1. pseudo-labels: the source encoder's poses, refined
    torch.manual_seed(cfg.seed)
    pseudo = (pseudo_labels(G, E, x, cfg, out / "pseudo.pt", progress)  # the source's encoder
              if cfg.lambda_pose > 0 else None)
    lab = (torch.from_numpy(np.asarray(train_labels[:cfg.frames]).astype(np.int64))
           if cfg.lambda_label > 0 else None)
    if cfg.encoder_nf:  # an encoder of another width, pruned from or widened from this one
        state = {**state, "model_config": {**state["model_config"], "encoder_nf": cfg.encoder_nf}}
        E = (narrowed if cfg.encoder_nf <= E.width else widened)(E, cfg.encoder_nf)
    # 2. the encoder fitted to them (and to the labels, the frames), G frozen
    device = checkpoint.pick_device(device)
    G, E = G.to(device), E.to(device)
    xt = torch.from_numpy(x)
    ut = (torch.from_numpy(np.ascontiguousarray(user_x, dtype=np.float32))
          if cfg.lambda_user > 0 else None)
    run = _Distillation(cfg, source, state, previous, self_fit, G, E,
                        torch.optim.Adam(E.parameters(), cfg.lr, betas=(0.5, 0.999)),
                        torch.Generator().manual_seed(cfg.seed), out, val, tau)
    if resume and (out / "last.pt").is_file():
        run.resume()
    run.start = time.monotonic()
    E.train()
    if val is not None and run.it == 0 and run.validate():
        run.save(out / "best.pt")  # the shipped encoder, for comparison
    stats = _train_encoder(run, xt, pseudo, lab, ut, device, progress)
    if not (out / "best.pt").is_file():
        run.save(out / "best.pt")
    summary = {"iterations": run.it, "seconds": round(run.seconds(), 1),
               "best_score": run.best, "pseudo_label_frames": len(x), "last": stats,
               "val": [h for h in run.history if h["kind"] == "val"]}
    write_json(out / "summary.json", summary)
    plot_curves(run.history, out / "curves.png")
    return summary
