"""Training InSeGAN: one iteration = discriminator step, generator step, encoder step.

    inseggan train --data data/cylinder --out runs/cylinder --minutes 60   (config cpu_spheres)
    torchrun --nproc_per_node 2 -m inseggan_ros.cli.main train ...        (DistributedDataParallel)

Per iteration (the paper, Sec. 3):
  1. D: BCE(D(x_real), 1) + BCE(D(G(Z)), 0), Z ~ N(0, I), n codes per image;
  2. G: BCE(D(G(Z)), 1) (non-saturating);
  3. E, generator frozen: L_a (codes, or for explicit templates the pose features a render
     depends on, vs. the best-matched encoded ones) + l_i L_i (derenderer vs.
     mean instance feature) + l_p L_p (||G(Z) - G(E(G(Z)))||_1), plus, in this project's
     configs, l_r ||x_real - G(E(x_real))||_1: the encoder also learns to explain *real* frames
     through the frozen generator (analysis by synthesis on the data it will see at run time).
Checkpoints (last.pt every `checkpoint_every` iterations and at the end, best.pt on the best
validation score) are written atomically; a killed run resumes from last.pt with `--resume`.
Logs: log.jsonl (one line per `log_every` iterations), samples/*.png, curves.png, summary.json.
"""
from __future__ import annotations

import contextlib
import copy
import gc
import json
import math
import os
import random
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from inseggan_ros.core import checkpoint
from inseggan_ros.learning import losses
from inseggan_ros.evaluation.evaluate import write_json
from inseggan_ros.runtime.model import ConvexGenerator, ModelConfig, TemplateGenerator, build


@dataclass(frozen=True)
class TrainConfig:
    model: ModelConfig = field(default_factory=ModelConfig)
    batch_size: int = 64
    lr_g: float = 2e-4
    lr_d: float = 2e-4
    lr_e: float = 1e-3
    lr_template: float = 0.0  # learning rate of the explicit template (0 = lr_g)
    betas: tuple[float, float] = (0.5, 0.999)
    lambda_i: float = 1.0
    lambda_p: float = 1.0
    lambda_real: float = 0.0  # real-frame reconstruction, G(E(x_real)) vs x_real
    real_trains_generator: bool = False  # that loss also trains G (an autoencoder on real data)
    real_trains_template: bool = True  # ... including an explicit template (else: GAN only)
    r1_gamma: float = 0.0  # R1 penalty weight (0 = off)
    recon_levels: int = 1  # L_p and the real-frame loss: L1 over this many pyramid levels
    background_weight: float = 1.0  # real-frame loss: weight of pixels that are floor
    compactness: float = 0.0  # explicit template: weight of its spread (`template_spread`)
    template_init: str = "data"  # convex template: start as the box the training frames
    # suggest ("data", `init_from_data`) or as the generator's fixed default box ("default")
    matching: str = "hungarian"
    augment: bool = True  # random flips
    rotate: bool = False  # and small rotations (+-20 degrees)
    max_iterations: int = 100_000
    max_minutes: float = 0.0  # wall-clock budget; 0 = none
    eval_every: int = 250
    checkpoint_every: int = 250
    log_every: int = 25
    eval_frames: int = 200
    divergence_threshold: float = 40.0
    seed: int = 0

    def __post_init__(self):
        if self.batch_size < 2:
            raise ValueError(f"batch_size must be >= 2, got {self.batch_size}")
        if not 1 <= self.recon_levels <= 6:
            raise ValueError("recon_levels must be in 1..6 (64 px down to 2), got "
                             f"{self.recon_levels}")
        if self.template_init not in ("data", "default"):
            raise ValueError(f"template_init {self.template_init!r} invalid; valid: data, default")
        if self.matching not in losses.MATCHINGS:
            raise ValueError(f"matching {self.matching!r} invalid; valid: "
                             f"{', '.join(losses.MATCHINGS)}")
        for name in ("lr_g", "lr_d", "lr_e"):  # lr_template may be 0 (= lr_g)
            if not 0 < getattr(self, name) < 1:
                raise ValueError(f"{name} must be in (0, 1), got {getattr(self, name)}")

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "TrainConfig":
        d = dict(d)
        d["model"] = ModelConfig.from_dict(d["model"])
        d["betas"] = tuple(d["betas"])
        return TrainConfig(**d)


CONFIGS: dict[str, TrainConfig] = {
    # The paper's full recipe, for a GPU: nf = 64, batch 128, features averaged before rendering.
    "paper": TrainConfig(model=ModelConfig(nf=64, composite="average"), batch_size=128),
    # The paper's recipe scaled to a CPU: nf = 32, batch 64.
    "paper_cpu": TrainConfig(model=ModelConfig(nf=32, composite="average"), batch_size=64),
    # The default: a rod of learned spheres, height maps in closed form (docs/experiments.md).
    "cpu_spheres": TrainConfig(model=ModelConfig(nf=32, latent_dim=16, composite="zbuffer",
                                                 renderer="spheres", spectral_norm=True,
                                                 radius_profile="monotone"),
                               batch_size=32, lambda_real=1.0, real_trains_generator=True,
                               r1_gamma=10.0, lr_template=0.003, recon_levels=4,
                               compactness=5.0),
    # A template for any rigid part: a union of convex pieces (flat faces, edges, holes), full
    # 3D poses, resting on the floor or above it (`floor_contact`: without it the first run's
    # instances sank under the floor); it starts as the box the training frames suggest
    # (`init_from_data`).
    "cpu_convex": TrainConfig(model=ModelConfig(nf=32, latent_dim=16, composite="zbuffer",
                                                renderer="convex", spectral_norm=True,
                                                floor_contact=True),
                              batch_size=32, lambda_real=1.0, real_trains_generator=True,
                              r1_gamma=10.0, lr_template=0.003, recon_levels=4,
                              compactness=5.0),
    # The learned renderer, instances rendered alone and z-buffered in training as at test
    # time, and the encoder also fitted to real frames through the frozen generator.
    "cpu": TrainConfig(model=ModelConfig(nf=32, latent_dim=16, composite="zbuffer",
                                         render_bias=-2.5),
                       batch_size=32, lambda_real=1.0),
}


def get_config(name: str, **overrides) -> TrainConfig:
    if name not in CONFIGS:
        raise ValueError(f"unknown config {name!r}; valid: {', '.join(CONFIGS)}")
    cfg = CONFIGS[name]
    model_keys = set(ModelConfig.__dataclass_fields__)
    m = {k: v for k, v in overrides.items() if k in model_keys and v is not None}
    t = {k: v for k, v in overrides.items() if k not in model_keys and v is not None}
    return replace(cfg, model=replace(cfg.model, **m), **t)


# ----------------------------------------------------------------------------- helpers
def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


@contextlib.contextmanager
def _frozen(module):
    """Gradients flow through `module` but its weights get none."""
    flags = [p.requires_grad for p in module.parameters()]
    for p in module.parameters():
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p, f in zip(module.parameters(), flags):
            p.requires_grad_(f)


def _unwrap(m):
    return m.module if hasattr(m, "module") else m


@dataclass
class Run:
    """Everything a training run owns; `state()` is what a checkpoint stores."""

    cfg: TrainConfig
    G: torch.nn.Module
    D: torch.nn.Module
    E: torch.nn.Module
    opt_g: torch.optim.Optimizer
    opt_d: torch.optim.Optimizer
    opt_e: torch.optim.Optimizer
    iteration: int = 0
    elapsed: float = 0.0  # training seconds before this process
    best: float = -math.inf
    tau: float = -0.5
    history: list = field(default_factory=list)
    resets: int = 0
    good_g: dict | None = None

    def state(self, prep_cfg: dict, data_info: dict) -> dict:
        return {
            "model_config": self.cfg.model.to_dict(), "train_config": self.cfg.to_dict(),
            "preprocess_config": prep_cfg, "data": data_info, "tau": self.tau,
            "iteration": self.iteration, "elapsed_seconds": self.elapsed, "best": self.best,
            "history": self.history, "resets": self.resets,
            "generator": _unwrap(self.G).state_dict(), "encoder": _unwrap(self.E).state_dict(),
            "discriminator": _unwrap(self.D).state_dict(),
            "optimizers": {"g": self.opt_g.state_dict(), "d": self.opt_d.state_dict(),
                           "e": self.opt_e.state_dict()},
            "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(),
                    "python": random.getstate()},
        }


def weights_checksum(run: Run) -> str:
    import hashlib

    h = hashlib.sha256()
    for m in (run.G, run.D, run.E):
        for t in _unwrap(m).state_dict().values():
            h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def make_run(cfg: TrainConfig, device: str) -> Run:
    G, D, E = build(cfg.model)
    G, D, E = G.to(device), D.to(device), E.to(device)
    explicit = G.template_parameters
    template = [p for name, p in G.named_parameters() if name in explicit]
    rest = [p for name, p in G.named_parameters() if name not in explicit]
    groups = [{"params": rest}]
    if template:  # an explicit template needs far larger steps than network weights
        groups.append({"params": template, "lr": cfg.lr_template or cfg.lr_g})
    return Run(cfg, G, D, E,
               torch.optim.Adam(groups, cfg.lr_g, betas=cfg.betas),
               torch.optim.Adam(D.parameters(), cfg.lr_d, betas=cfg.betas),
               torch.optim.Adam(E.parameters(), cfg.lr_e, betas=cfg.betas))


def restore(run: Run, state: dict) -> None:
    _unwrap(run.G).load_state_dict(state["generator"])
    _unwrap(run.D).load_state_dict(state["discriminator"])
    _unwrap(run.E).load_state_dict(state["encoder"])
    run.opt_g.load_state_dict(state["optimizers"]["g"])
    run.opt_d.load_state_dict(state["optimizers"]["d"])
    run.opt_e.load_state_dict(state["optimizers"]["e"])
    run.iteration, run.elapsed = state["iteration"], state["elapsed_seconds"]
    run.best, run.tau, run.history = state["best"], state["tau"], state["history"]
    run.resets = state.get("resets", 0)
    torch.set_rng_state(state["rng"]["torch"])
    np.random.set_state(state["rng"]["numpy"])
    random.setstate(state["rng"]["python"])


# ----------------------------------------------------------------------------- one iteration
def train_step(run: Run, real: torch.Tensor, amp: bool = False) -> dict:
    cfg, G, D, E = run.cfg, run.G, run.D, run.E
    B, n, d = real.shape[0], cfg.model.n_instances, cfg.model.latent_dim
    z = torch.randn(B, n, d, device=real.device)
    autocast = torch.autocast("cuda", dtype=torch.bfloat16, enabled=amp)

    # 1. discriminator: real -> 1, generated -> 0 (one forward over both halves)
    with autocast:
        fake, mean_f = G(z, return_features=True)
    real_in = real.requires_grad_(cfg.r1_gamma > 0)
    with autocast:
        logits = D(torch.cat([real_in, fake.detach()]))
    loss_d = losses.d_loss(logits[:B].float(), logits[B:].float())
    if cfg.r1_gamma > 0:
        loss_d = loss_d + cfg.r1_gamma / 2 * losses.r1_penalty(logits[:B].float(), real_in)
    run.opt_d.zero_grad(set_to_none=True)
    loss_d.backward()
    run.opt_d.step()
    real = real.detach()

    # 2. generator: non-saturating (+ a compactness prior that keeps an explicit template one
    # object around its centre, instead of several objects that would pose together)
    with autocast:
        loss_g = losses.g_loss(D(fake).float())
    g0 = _unwrap(G)
    if cfg.compactness > 0 and isinstance(g0, TemplateGenerator):
        loss_g = loss_g + cfg.compactness * g0.template_spread()
    run.opt_g.zero_grad(set_to_none=True)
    loss_g.backward()
    run.opt_g.step()

    # 3. encoder, generator frozen (gradients flow through G to E, G's weights do not change)
    x_gen = fake.detach()
    target_f = mean_f.detach() if mean_f is not None else None
    g = _unwrap(G)
    joint = cfg.lambda_real > 0 and not cfg.real_trains_generator
    with _frozen(g), autocast:
        enc_in = torch.cat([x_gen, real]) if joint else x_gen
        z_hat_all, h_all = E(enc_in, return_features=True)
        z_hat, h = z_hat_all[:B], h_all[:B]
        l_a = losses.alignment_loss(g.alignment_features(z).float(),
                                    g.alignment_features(z_hat).float(), cfg.matching)
        l_i = (F.mse_loss(h.float(), target_f.float()) if target_f is not None
               else torch.zeros((), device=real.device))  # explicit templates: no features
        l_p = losses.pyramid_l1(g(z_hat).float(), x_gen.float(), cfg.recon_levels)
        loss_e = l_a + cfg.lambda_i * l_i + cfg.lambda_p * l_p
        l_r = torch.zeros(())
        if joint:
            l_r = losses.pyramid_l1(g(z_hat_all[B:]).float(), real.float(), cfg.recon_levels,
                                    cfg.background_weight)
            loss_e = loss_e + cfg.lambda_real * l_r
    run.opt_e.zero_grad(set_to_none=True)
    loss_e.backward()
    run.opt_e.step()

    # 4. (optional) real frames through E and G, both trained: analysis by synthesis on the
    # data itself; a rigidly posed shared template per code keeps the instances apart
    if cfg.lambda_real > 0 and cfg.real_trains_generator:
        with autocast:
            l_r = losses.pyramid_l1(G(E(real)).float(), real.float(),  # through DDP if distributed
                                    cfg.recon_levels, cfg.background_weight)
        run.opt_e.zero_grad(set_to_none=True)
        run.opt_g.zero_grad(set_to_none=True)
        (cfg.lambda_real * l_r).backward()
        if not cfg.real_trains_template:  # the template learns from the GAN alone
            for group in run.opt_g.param_groups[1:]:  # the template's group, if there is one
                for p in group["params"]:
                    p.grad = None  # Adam skips parameters without a gradient
        run.opt_e.step()
        run.opt_g.step()
    return {"loss_d": loss_d.item(), "loss_g": loss_g.item(), "l_a": l_a.item(),
            "l_i": l_i.item(), "l_p": l_p.item(), "l_real": l_r.item()}


def guard_divergence(run: Run, stats: dict) -> bool:
    """Reset G (and D) to the last good weights when the adversarial losses blow up."""
    bad = not all(math.isfinite(v) for v in stats.values()) or \
        max(stats["loss_g"], stats["loss_d"]) > run.cfg.divergence_threshold
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():  # all ranks reset together, or none
        flag = torch.tensor(float(bad), device=next(_unwrap(run.G).parameters()).device)
        dist.all_reduce(flag, op=dist.ReduceOp.MAX)
        bad = bool(flag.item())
    if bad and run.good_g is not None:
        _unwrap(run.G).load_state_dict(run.good_g["g"])
        _unwrap(run.D).load_state_dict(run.good_g["d"])
        run.opt_g.state.clear()
        run.opt_d.state.clear()
        run.resets += 1
    elif not bad and run.iteration % 50 == 0:
        run.good_g = {"g": copy.deepcopy(_unwrap(run.G).state_dict()),
                      "d": copy.deepcopy(_unwrap(run.D).state_dict())}
    return bad


# ----------------------------------------------------------------------------- evaluation
@torch.no_grad()
def evaluate(run: Run, val: dict, device: str, frames: int) -> dict:
    """Validation: mIoU at the calibrated tau when labels exist, and reconstruction error.
    Without labels (a bag) tau comes from the frames themselves (`selfcheck.tau_from_frames`:
    the rendered foreground that best matches the input's), so it follows the model."""
    from inseggan_ros.runtime.segment import calibrate_tau, infer
    from inseggan_ros.evaluation.selfcheck import tau_from_frames

    G, E = _unwrap(run.G).eval(), _unwrap(run.E).eval()
    x = torch.from_numpy(val["x"][:frames]).to(device)
    outs = [infer(G, E, x[i:i + 100]) for i in range(0, len(x), 100)]
    renders = torch.cat([o["renders"] for o in outs])
    recon = torch.cat([o["reconstruction"] for o in outs])
    fg = torch.from_numpy(val["fg"][:frames]).to(device)
    labels = val.get("labels")
    labels = labels[:frames] if labels is not None else None
    if labels is not None:
        tau, scores = calibrate_tau(renders, fg, labels)
    elif fg.any():
        tau, scores = tau_from_frames(renders, fg, val.get("config"))
    else:  # empty bins only: nothing to calibrate on
        tau, scores = run.tau, {run.tau: 0.0}
    result = {"recon_l1": float((recon - x).abs().mean()), "tau": tau}
    if labels is not None:  # calibration scored every tau by mIoU already
        result["miou"] = scores[tau]
    else:  # how well the rendered foreground matches the input's, at that tau
        result["fg_iou"] = scores[tau]
    G.train()
    E.train()
    return result


def save_samples(run: Run, x: torch.Tensor, path: Path, tau: float) -> None:
    """PNG grid: input | reconstruction | labels | each instance rendered alone."""
    from inseggan_ros.core import viz
    from inseggan_ros.runtime.segment import infer, labels_from_renders

    G, E = _unwrap(run.G).eval(), _unwrap(run.E).eval()
    out = infer(G, E, x)
    fg = x[:, 0] > -1 + 1e-4
    labels = labels_from_renders(out["renders"], tau, fg).cpu().numpy()
    rows = []
    for i in range(len(x)):
        row = [viz.gray(x[i, 0].cpu().numpy()), viz.gray(out["reconstruction"][i, 0].cpu().numpy()),
               viz.colorize_labels(labels[i])]
        row += [viz.gray(r) for r in out["renders"][i].cpu().numpy()]
        rows.append(row)
    n = out["renders"].shape[1]
    viz.save_sheet(path, rows, col_titles=["input", "reconstruction", "labels"] +
                   [f"instance {k + 1}" for k in range(n)], cell_inches=1.2, dpi=70)
    G.train()
    E.train()


def plot_curves(history: list, path: Path) -> None:
    from inseggan_ros.core.viz import plot_history

    plot_history(history, path, [("adversarial", "train", ("loss_d", "loss_g")),
                                 ("encoder", "train", ("l_a", "l_i", "l_p", "l_real")),
                                 ("validation", "val", ("miou", "recon_l1", "fg_iou", "tau"))])


# ----------------------------------------------------------------------------- the loop
def torchrun_env() -> tuple[int, int, int]:
    """(world size, rank, local rank) as torchrun sets them; (1, 0, 0) in a plain process."""
    return tuple(int(os.environ.get(k, d)) for k, d in
                 (("WORLD_SIZE", "1"), ("RANK", "0"), ("LOCAL_RANK", "0")))


def train(cfg: TrainConfig, train_data: dict, val_data: dict | None, out: Path,
          prep_cfg: dict, data_info: dict, device: str = "auto", resume: bool = False,
          progress: bool = True) -> dict:
    """Train until max_iterations or max_minutes; returns the summary (also summary.json).

    Under torchrun (WORLD_SIZE > 1) it joins the process group, or opens one, and destroys the
    group it opened before returning: a gloo group left to the interpreter's exit may abort the
    process ("terminate called without an active exception") while its threads still run. The
    ranks leave together (a barrier after rank 0's last write), and the DDP wrappers, which
    hold the group too, are collected first, so that nothing keeps it past its destruction.
    """
    import torch.distributed as dist

    device = checkpoint.pick_device(device)
    opened = torchrun_env()[0] > 1 and dist.is_available() and not dist.is_initialized()
    if opened:
        dist.init_process_group("nccl" if device.startswith("cuda") else "gloo")
    try:
        return _train(cfg, train_data, val_data, out, prep_cfg, data_info, device, resume,
                      progress)
    finally:
        if opened and dist.is_initialized():
            gc.collect()  # the DDP wrappers (and their reducers' hold on the group) go now
            dist.destroy_process_group()
            gc.collect()


@dataclass
class _Session:
    """What the phases of one training process share besides its `Run`: where it writes, whether
    it is the main rank, the validation frames and samples, and its clock and image counts."""

    run: Run
    out: Path
    device: str
    is_main: bool
    prep_cfg: dict
    data_info: dict
    val_data: dict | None
    sample_x: torch.Tensor | None = None  # the validation frames drawn in samples/*.png
    start: float = 0.0  # time.monotonic() when this process began training
    seen: int = 0  # images trained on by this process
    window_t: float = 0.0  # the throughput's window: its start, its images
    window_n: int = 0

    def elapsed(self) -> float:
        return self.run.elapsed + time.monotonic() - self.start

    def checkpoint_now(self, best: bool = False) -> None:
        if not self.is_main:
            return
        state = self.run.state(self.prep_cfg, self.data_info)
        state["elapsed_seconds"] = self.elapsed()
        checkpoint.save(self.out / "last.pt", state)
        if best:
            checkpoint.save(self.out / "best.pt", state)

    def validate(self) -> bool:
        """Validation record (and samples, curves); returns whether it is the best so far."""
        run, out = self.run, self.out
        v = evaluate(run, self.val_data, self.device, run.cfg.eval_frames)
        rec = {"kind": "val", "iteration": run.iteration, "seconds": round(self.elapsed(), 1),
               **v}
        run.history.append(rec)
        with open(out / "log.jsonl", "a") as f:
            f.write(json.dumps(rec) + "\n")
        score = v.get("miou", -v["recon_l1"])
        improved = score > run.best
        if improved:
            run.best, run.tau = score, v["tau"]
        save_samples(run, self.sample_x, out / "samples" / f"iter_{run.iteration:06d}.png",
                     v["tau"])
        plot_curves(run.history, out / "curves.png")
        tqdm.write(f"iter {run.iteration}: " + ", ".join(
            f"{k} {val:.4f}" for k, val in v.items()) + (" (best)" if improved else ""))
        return improved


def _resume(run: Run, out: Path, resume: bool, device: str, is_main: bool) -> None:
    """Continue from out/last.pt with `resume` (the same model config only); without it, refuse
    a folder that holds a run."""
    last = out / "last.pt"
    if resume and last.is_file():
        state = checkpoint.load(last, map_location=device)
        saved = TrainConfig.from_dict(state["train_config"])
        if saved.model != run.cfg.model:
            raise ValueError(f"{last}: was trained with {saved.model}, not {run.cfg.model}; "
                             "resume with the same config or choose another --out")
        restore(run, state)
        if is_main:
            print(f"resumed from {last} at iteration {run.iteration}")
    elif last.is_file():
        raise FileExistsError(f"{out} holds a run already (last.pt): pass --resume to continue "
                              "it, or choose another --out")


def _loader(cfg: TrainConfig, train_data: dict, rank: int, iteration: int, distributed: bool,
            amp: bool):
    """-> (the training frames' DataLoader, its sampler): drawn with replacement from a
    generator seeded by rank and iteration, or a DistributedSampler's share."""
    from torch.utils.data import DataLoader, RandomSampler

    from inseggan_ros.data.datasets import DepthTensorDataset

    dataset = DepthTensorDataset(train_data, augment=cfg.augment,
                                 rotation=20.0 if cfg.rotate else 0.0)
    gen = torch.Generator().manual_seed(cfg.seed * 1000 + rank + iteration)
    if distributed:
        from torch.utils.data.distributed import DistributedSampler

        sampler = DistributedSampler(dataset, seed=cfg.seed + iteration, drop_last=True)
    else:
        sampler = RandomSampler(dataset, replacement=True, num_samples=10**9, generator=gen)
    loader = DataLoader(dataset, batch_size=cfg.batch_size, sampler=sampler, drop_last=True,
                        num_workers=0, pin_memory=amp)
    return loader, sampler


def _log_train(s: _Session, stats: dict, bar) -> None:
    """The training record of the last `log_every` iterations (throughput, losses)."""
    run = s.run
    now = time.monotonic()
    ips = s.window_n / max(now - s.window_t, 1e-9)
    s.window_t, s.window_n = now, 0
    rec = {"kind": "train", "iteration": run.iteration, "seconds": round(s.elapsed(), 1),
           "images_per_s": round(ips, 1), "resets": run.resets,
           **{k: round(v, 5) for k, v in stats.items()}}
    run.history.append(rec)
    if s.is_main:
        with open(s.out / "log.jsonl", "a") as f:
            f.write(json.dumps(rec) + "\n")
        bar.set_postfix(it=run.iteration, d=f"{stats['loss_d']:.2f}",
                        g=f"{stats['loss_g']:.2f}",
                        a=f"{stats['l_a']:.2f}", p=f"{stats['l_p']:.3f}",
                        r=f"{stats['l_real']:.3f}", ips=f"{ips:.0f}")


def _iterate(s: _Session, batches, loader, sampler, distributed: bool, amp: bool,
             progress: bool) -> dict:
    """Iterations until max_iterations or max_minutes, logged, validated and checkpointed (from
    the starting point's validation on) -> the last iteration's losses."""
    run, cfg = s.run, s.run.cfg
    budget = cfg.max_minutes * 60 if cfg.max_minutes > 0 else math.inf
    s.start = s.window_t = time.monotonic()
    # with a time budget the bar counts its seconds (the iteration cap is then only a bound)
    by_time = budget < math.inf
    bar = tqdm(total=round(budget) if by_time else cfg.max_iterations,
               initial=min(round(run.elapsed), round(budget)) if by_time else run.iteration,
               desc="training", unit="s" if by_time else "it",
               disable=not (progress and s.is_main), dynamic_ncols=True)
    stats = {}
    if s.is_main and s.val_data is not None and run.iteration == 0:
        # the starting point, so that curves show what training changed; it is best.pt until a
        # later validation scores higher (a run that never does keeps its starting weights)
        s.checkpoint_now(best=s.validate())
    try:
        while run.iteration < cfg.max_iterations and s.elapsed() < budget:
            try:
                real = next(batches)
            except StopIteration:
                if distributed:
                    sampler.set_epoch(run.iteration)
                batches = iter(loader)
                real = next(batches)
            stats = train_step(run, real.to(s.device, non_blocking=True), amp)
            run.iteration += 1
            s.seen += real.shape[0]
            s.window_n += real.shape[0]
            guard_divergence(run, stats)
            bar.update(min(round(s.elapsed()), bar.total) - bar.n if by_time else 1)
            if run.iteration % cfg.log_every == 0:
                _log_train(s, stats, bar)
            if run.iteration % cfg.eval_every == 0 or run.iteration == cfg.max_iterations:
                improved = s.is_main and s.val_data is not None and s.validate()
                s.checkpoint_now(best=improved)
            elif run.iteration % cfg.checkpoint_every == 0:
                s.checkpoint_now()
    finally:
        bar.close()
    return stats


def _finish(s: _Session, stats: dict, world_size: int, distributed: bool) -> dict:
    """The last weights validated (when the last validation was earlier) and checkpointed, the
    ranks' weights' checksums gathered -> the summary (also summary.json, curves.png)."""
    run, out = s.run, s.out
    # a run stopped by its time budget between validations: validate its last weights too, so
    # that their tau (calibrated from the frames on a bag) is the one stored
    validated = [h["iteration"] for h in run.history if h["kind"] == "val"]
    improved = (s.is_main and s.val_data is not None and bool(validated)
                and validated[-1] != run.iteration and s.validate())
    s.checkpoint_now(best=improved or not (out / "best.pt").exists())
    checksums = [weights_checksum(run)]
    if distributed:  # every rank reports the checksum of its weights: DDP keeps them identical
        import torch.distributed as dist

        checksums = [None] * dist.get_world_size()
        dist.all_gather_object(checksums, weights_checksum(run))
    ips = s.seen / max(time.monotonic() - s.start, 1e-9)
    summary = {"iterations": run.iteration, "seconds": round(s.elapsed(), 1),
               "images_per_s_this_process": round(ips, 1),
               "best_score": run.best, "tau": run.tau, "resets": run.resets,
               "device": s.device, "world_size": world_size,
               "weights_sha256_per_rank": checksums, "last": stats}
    if s.is_main:
        write_json(out / "summary.json", summary)
        if run.history:
            plot_curves(run.history, out / "curves.png")
    if distributed:  # no rank leaves (and destroys its group) while another still works
        dist.barrier()
    return summary


def _train(cfg, train_data, val_data, out, prep_cfg, data_info, device, resume, progress):
    world_size, rank, local_rank = torchrun_env()
    distributed = world_size > 1
    if distributed:
        if device.startswith("cuda"):
            device = f"cuda:{local_rank}"
            torch.cuda.set_device(device)
    out = Path(out)
    is_main = rank == 0
    seed_everything(cfg.seed + rank)
    run = make_run(cfg, device)
    _resume(run, out, resume, device, is_main)
    if run.iteration == 0 and cfg.template_init == "data" and isinstance(run.G, ConvexGenerator):
        run.G.init_from_data(train_data["x"], cfg.model.n_instances)  # of the data's size
    if distributed:
        from torch.nn.parallel import DistributedDataParallel as DDP

        ids = [torch.device(device).index] if device.startswith("cuda") else None
        run.G, run.D, run.E = (DDP(m, device_ids=ids) for m in (run.G, run.D, run.E))
    amp = device.startswith("cuda")
    loader, sampler = _loader(cfg, train_data, rank, run.iteration, distributed, amp)
    batches = iter(loader)
    if is_main:
        out.mkdir(parents=True, exist_ok=True)
        (out / "samples").mkdir(exist_ok=True)
        write_json(out / "config.json", cfg.to_dict())
    s = _Session(run, out, device, is_main, prep_cfg, data_info, val_data)
    if val_data is not None:
        s.sample_x = torch.from_numpy(val_data["x"][:6]).to(device)
    stats = _iterate(s, batches, loader, sampler, distributed, amp, progress)
    return _finish(s, stats, world_size, distributed)
