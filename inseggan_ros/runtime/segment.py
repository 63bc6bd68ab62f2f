"""Inference: depth frame -> instance labels, masks, reconstruction, per-instance scores (no ROS).

The paper's recipe: E(x) -> n codes; every code rendered alone, G_r(F(z_i)); each render median-
and Gaussian-filtered; per pixel the instance whose render is nearest the camera (largest height)
wins (z-buffer); a pixel is background where every render is below the threshold tau. Labels are
made at the model's 64 x 64 and mapped back to the input's pixels, on input foreground only.
tau is calibrated on validation data and stored in the checkpoint (no per-object hand tuning).
With centre votes (`centres.py`, `centre_votes: on`) the instances come from a small network's
heatmap of part centres instead, each named after the render it overlaps most; the renders still
give the scores and the reconstruction.

    seg = Segmenter.from_checkpoint("models/cylinder/model.pt")
    out = seg(depth_m)            # any resolution, metres; 0 = no reading
    out.labels, out.masks, out.reconstruction, out.scores
"""
from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from inseggan_ros.core import checkpoint
from inseggan_ros.runtime.centres import (
    MIN_PIXELS, centre_labels, match_to_renders, net_from_state)
from inseggan_ros.runtime.label_head import head_labels, head_from_state
from inseggan_ros.core.metrics import mean_miou, miou_batch
from inseggan_ros.runtime.model import TemplateGenerator
from inseggan_ros.runtime.precision import CastCentreNet, CastEncoder, native_bfloat16
from inseggan_ros.runtime.preprocess import (
    PreprocessConfig, extend_labels, fill_labels_nearest, labels_to_full, prepare)
from inseggan_ros.runtime.refine import refine, refine_poses, start_poses
from inseggan_ros.core.settings import InferenceConfig
from inseggan_ros.runtime.smoothing import smooth_full, smooth_labels
from inseggan_ros.runtime.superpixels import (
    drop_small, drop_walls, frame_segments, split_labels, vote_labels)
from inseggan_ros.runtime.model import build_models

TAU_GRID = tuple(np.round(np.linspace(-0.95, 0.5, 30), 3))


def _median3(x: torch.Tensor) -> torch.Tensor:
    """3x3 median filter of (M, 1, H, W)."""
    patches = F.unfold(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3)
    return patches.median(dim=1).values.reshape(x.shape)


def _gauss(x: torch.Tensor, sigma: float = 0.8) -> torch.Tensor:
    r = torch.arange(-2, 3, dtype=x.dtype, device=x.device)
    k = torch.exp(-r ** 2 / (2 * sigma ** 2))
    k = k / k.sum()
    x = F.conv2d(F.pad(x, (2, 2, 0, 0), mode="replicate"), k.view(1, 1, 1, 5))
    return F.conv2d(F.pad(x, (0, 0, 2, 2), mode="replicate"), k.view(1, 1, 5, 1))


@torch.no_grad()
def infer(G, E, x: torch.Tensor, filtered: bool | None = None, refine_steps: int = 0,
          hypotheses: int = 1, keep: int = 0, swaps: int = 0) -> dict:
    """(B, 1, 64, 64) inputs -> single-instance renders (B, n, 64, 64), reconstruction, and the
    codes ("z") or, with test-time refinement, the poses ("pose").

    `filtered` (default: for the learned renderer only, whose renders are noisy; the explicit
    templates render clean edges that a blur would only soften) median- and Gauss-filters
    every render, as the reference code does. `refine_steps`, `hypotheses`, `keep`, `swaps`:
    test-time refinement (`refine_poses` from `start_poses`, also with 0 steps when there are
    several starts to choose from; for the learned renderer `refine` on the codes, from the
    encoder's codes only)."""
    explicit = isinstance(G, TemplateGenerator)
    if explicit and (refine_steps > 0 or hypotheses > 1):
        # the input and its symmetric images through the encoder in one batch
        pose = refine_poses(G, start_poses(G, E, x, hypotheses), x, refine_steps, keep=keep,
                            swaps=swaps)
        renders = G.render_poses(pose)
        return {"pose": pose, "renders": renders, "reconstruction": G.zbuffer(renders)}
    z = E(x)
    if refine_steps > 0:
        z = refine(G, z, x, refine_steps)
    renders = G.render_instances(z)
    if filtered is None:
        filtered = G.cfg.renderer == "learned"
    if filtered:
        B, n, H, W = renders.shape
        r = renders.reshape(B * n, 1, H, W)
        renders = _gauss(_median3(r)).reshape(B, n, H, W)
    # the explicit templates' composite is the z-buffer of their renders: no second render
    recon = G.zbuffer(renders) if explicit and not filtered else G(z)
    return {"z": z, "renders": renders, "reconstruction": recon}


def labels_from_renders(renders: torch.Tensor, tau: float, fg: torch.Tensor | None = None,
                        fill: bool = True):
    """z-buffer: (B, n, H, W) renders -> (B, H, W) labels (0 = background, 1..n).

    With the input's foreground `fg`, labels are kept on it only, and (`fill`) a foreground
    pixel that no render reaches (every render below tau there: a slightly too small or
    misplaced render) takes the label of the nearest labelled pixel, so that every object pixel
    gets an instance."""
    top, idx = renders.max(dim=1)
    labels = (idx + 1).to(torch.uint8)
    labels[top < tau] = 0
    if fg is None:
        return labels
    labels[~fg] = 0
    if fill:
        labels = _fill_nearest(labels, fg)
    return labels


def _fill_nearest(labels: torch.Tensor, fg: torch.Tensor) -> torch.Tensor:
    """`preprocess.fill_labels_nearest` on every frame that has a label and a hole to fill."""
    lab, fgn = labels.cpu().numpy(), fg.cpu().numpy()
    for b in range(len(lab)):
        if (fgn[b] & (lab[b] == 0)).any() and lab[b].any():
            lab[b] = fill_labels_nearest(lab[b], fgn[b])
    return torch.from_numpy(lab).to(labels.device)


def instance_scores(renders: torch.Tensor, labels: torch.Tensor, tau: float) -> torch.Tensor:
    """Visible fraction of each instance: |won pixels| / |rendered pixels| in [0, 1] (B, n).

    1 = nothing lies on top of it (a good first pick), 0 = hidden or not rendered."""
    n = renders.shape[1]
    drawn = (renders >= tau).flatten(2).sum(-1).float()
    won = torch.stack([(labels == k + 1).flatten(1).sum(-1) for k in range(n)], 1).float()
    return torch.where(drawn > 0, won / drawn.clamp_min(1), torch.zeros_like(drawn))


def calibrate_tau(renders: torch.Tensor, fg: torch.Tensor, labels_gt: np.ndarray | None = None,
                  grid=TAU_GRID) -> tuple[float, dict]:
    """Choose tau on validation frames.

    With ground truth: the tau of the best mean mIoU. Without: the tau whose rendered foreground
    (max render >= tau) best matches the input foreground (IoU) - the reconstruction criterion."""
    scores = {}
    top = renders.max(dim=1).values
    for tau in grid:
        if labels_gt is not None:
            pred = labels_from_renders(renders, tau, fg).cpu().numpy()
            scores[tau] = float(mean_miou(miou_batch(pred, labels_gt)))
        else:
            drawn = top >= tau
            inter = (drawn & fg).flatten(1).sum(-1).float()
            union = (drawn | fg).flatten(1).sum(-1).float().clamp_min(1)
            scores[tau] = float((inter / union).mean())
    best = max(scores, key=lambda t: (scores[t], -abs(t)))
    return float(best), scores


@dataclass
class Segmentation:
    labels: np.ndarray  # (H, W) uint8 at the input resolution, 0 = background
    reconstruction: np.ndarray | None  # (H, W) float32 metres, the model's re-rendered depth
    scores: np.ndarray  # (n,) visible fraction per instance
    labels64: np.ndarray  # (64, 64) at the model's resolution
    x64: np.ndarray  # (64, 64) the model input
    roi: tuple[int, int, int, int]  # the bin region used (x0, y0, x1, y1)
    floor_depth: float  # metres
    renders64: np.ndarray | None = None  # (n, 64, 64) each instance rendered alone, [-1, 1]
    fg64: np.ndarray | None = None  # (64, 64) bool, the model input's foreground
    reconstruction64: np.ndarray | None = None  # (64, 64) the renders z-buffered, [-1, 1]

    @property
    def masks(self) -> np.ndarray:
        """(n, H, W) bool, one per instance: labels == k + 1."""
        n = len(self.scores)
        return self.labels[None] == np.arange(1, n + 1, dtype=np.uint8)[:, None, None]


class Segmenter:
    """A trained model + its preprocessing + tau + its test-time settings (`InferenceConfig`):
    depth frames in, segmentations out.

    `centre_net`: the model's centre votes (`centres.py`), used where the settings say
    `centre_votes: on`.

    `superpixel_thread`: what depends on the input frame alone, the centre votes' net and the
    frame's two graph segmentations (`superpixels.frame_segments`), is made in a second thread
    while the encoder and the renders run in this one; the labels are the same, the frame's
    latency lower where a second core is free (docs/benchmarks.md).

    `traced`: the encoder and the centre-vote net run as traced TorchScript graphs
    (`traced.Traced`): the same numbers, sooner (the segmenter node turns it on)."""

    def __init__(self, G, E, model_cfg, prep_cfg, tau: float, device: str = "cpu",
                 inference: InferenceConfig = InferenceConfig(), label_head=None,
                 superpixel_thread: bool = False, centre_net=None, traced: bool = False):
        self.G, self.E = G.eval().to(device), E.eval().to(device)
        self.label_head = label_head.eval().to(device) if label_head is not None else None
        self.centre_net = centre_net.eval().to(device) if centre_net is not None else None
        for p in self.G.parameters():  # test-time refinement optimises codes, never weights
            p.requires_grad_(False)
        self.model_cfg, self.prep_cfg, self.tau, self.device = model_cfg, prep_cfg, tau, device
        self.inference = inference
        self.stored_settings = True  # `inference` is what the model ships (see from_checkpoint)
        self._cast = {}  # (net's name, precision) -> its copy that computes in it
        self.superpixel_thread = superpixel_thread
        self.traced = traced
        self._pool = None  # made on first use

    def check(self, cfg: InferenceConfig) -> None:
        """Raises ValueError, naming the setting and what is valid, if this model cannot run
        with `cfg`: test-time refinement moves a rod's axis (or a learned renderer's codes),
        and a convex template has no pose fit (one tried, Adam on its six pose numbers,
        lowered the mIoU: docs/experiments.md, 2026-11-26)."""
        if cfg.refine_steps > 0 and self.G.cfg.renderer == "convex":
            raise ValueError(f"refine_steps {cfg.refine_steps}: this model's template is "
                             "convex pieces, which have no test-time pose fit; valid: 0 (its "
                             "starting points and smoothing still apply)")
        if cfg.label_head == "on" and self.label_head is None:
            raise ValueError("label_head on: this model has no label head; valid: off")
        if cfg.centre_votes == "on" and self.centre_net is None:
            raise ValueError("centre_votes on: this model has no centre-vote network "
                             "(`inseggan centres` makes one); valid: off")

    def encoder_changed(self) -> None:
        """Call after changing E's (or the centre net's) weights: their copies in other
        precisions are made anew."""
        self._cast.clear()

    def resolve_precision(self, precision: str) -> str:
        """`settings.PRECISIONS` -> what the encoder computes in: auto is bfloat16 where native."""
        if precision == "auto":
            return "bfloat16" if native_bfloat16(self.device) else "float32"
        return precision

    def _in_precision(self, name: str, cast, precision: str):
        """The net `self.<name>` in `precision` (`settings.PRECISIONS`): itself in float32 (or
        None), else `cast(net, dtype)`, made once per precision; with `traced`, called through
        its traced graphs."""
        net, precision = getattr(self, name), self.resolve_precision(precision)
        if net is None:
            return net
        if precision != "float32" and (name, precision) not in self._cast:
            self._cast[name, precision] = cast(net, getattr(torch, precision)).eval()
        net = net if precision == "float32" else self._cast[name, precision]
        if not self.traced:
            return net
        if (name, precision, "traced") not in self._cast:
            from inseggan_ros.runtime.traced import Traced

            self._cast[name, precision, "traced"] = Traced(net)
        return self._cast[name, precision, "traced"]

    def encoder(self, precision: str = "float32"):
        """The encoder in `precision` (`settings.PRECISIONS`)."""
        return self._in_precision("E", CastEncoder, precision)

    def centre_net_in(self, precision: str = "float32"):
        """The centre-vote net in `precision` (`settings.PRECISIONS`; its last layer stays
        float32, `precision.CastCentreNet`)."""
        return self._in_precision("centre_net", CastCentreNet, precision)

    def centre_votes(self, x, fg, n: int, precision: str = "float32",
                     founding: bool = False) -> torch.Tensor:
        """(B, 1, 64, 64) inputs and (B, 64, 64) foreground -> the centre votes' labels
        (B, 64, 64), before they are matched to the renders; with `founding`, also where a
        part's centre may be (`centres.centre_labels`). A peak is an instance only with at
        least MIN_PIXELS foreground pixels voting for it (`centres.decode`): the net was
        taught no centre for a part showing fewer, and a few stray pixels of an empty bin's
        foreground make no instance."""
        if self.centre_net is None:
            raise ValueError("centre_votes on: this model has no centre-vote network; "
                             "valid: off")
        x = torch.as_tensor(x, dtype=torch.float32, device=self.device)
        fg = torch.as_tensor(fg, dtype=torch.bool, device=self.device)
        return centre_labels(self.centre_net_in(precision), x, fg, n, MIN_PIXELS, founding)

    @staticmethod
    def from_checkpoint(path, device: str = "auto", tau: float | None = None,
                        superpixel_thread: bool = False) -> "Segmenter":
        """A checkpoint (training's or an exported model.pt) -> its Segmenter, with the
        checkpoint's preprocessing, tau (unless `tau` is given) and inference settings."""
        state = checkpoint.load(path)
        cfg, G, E = build_models(state, path)
        try:
            prep = PreprocessConfig.from_dict(state["preprocess_config"])
        except (KeyError, TypeError, ValueError) as e:
            raise checkpoint.CheckpointError(f"{path}: bad preprocessing config ({e})") from None
        try:  # models exported before label smoothing or `keep` existed: off, all
            inference = InferenceConfig.from_dict(state.get("inference", {}))
        except (TypeError, ValueError) as e:
            raise checkpoint.CheckpointError(f"{path}: bad inference settings ({e})") from None
        head = None
        if state.get("label_head") is not None:
            try:
                head = head_from_state(state["label_head"])
            except (KeyError, TypeError, ValueError, RuntimeError) as e:
                raise checkpoint.CheckpointError(f"{path}: bad label head ({e})") from None
        elif inference.label_head == "on":
            raise checkpoint.CheckpointError(f"{path}: its settings use a label head it does not "
                                             "have (label_head: on)")
        centres = None
        if state.get("centre_net") is not None:
            try:
                centres = net_from_state(state["centre_net"])
            except (KeyError, TypeError, ValueError, RuntimeError) as e:
                raise checkpoint.CheckpointError(f"{path}: bad centre-vote network ({e})") \
                    from None
        elif inference.centre_votes == "on":
            raise checkpoint.CheckpointError(f"{path}: its settings use a centre-vote network "
                                             "it does not have (centre_votes: on)")
        tau = float(state.get("tau", -0.5) if tau is None else tau)
        seg = Segmenter(G, E, cfg, prep, tau, device=checkpoint.pick_device(device),
                        inference=inference, label_head=head,
                        superpixel_thread=superpixel_thread, centre_net=centres)
        # a training checkpoint stores no settings: a parameters file then applies over
        # realtime.yaml's (`settings.file_base`), not over these bare defaults
        seg.stored_settings = "inference" in state
        return seg

    @torch.no_grad()
    def segment_batch(self, x: np.ndarray | torch.Tensor, fg=None, tau: float | None = None,
                      settings: InferenceConfig | None = None, segments=None,
                      centres=None, timings: dict | None = None) -> dict:
        """(B, 1, 64, 64) prepared inputs -> labels (B, 64, 64) uint8, renders, scores, recon.
        `tau` and `settings` override the model's. `segments`: each frame's
        `superpixels.frame_segments` made beforehand (a list, or a Future of one); `centres`:
        the centre votes made beforehand (`centre_votes`, its labels or with `founding` its
        pair, or a Future of them). `timings`: a dict that gets the seconds the networks took
        ("network")."""
        cfg = self.inference if settings is None else settings
        x = torch.as_tensor(x, dtype=torch.float32, device=self.device)
        out = self.model_labels(x, fg, tau, cfg, centres, timings)
        return self.vote_and_split(out, x, cfg, tau, segments)

    @torch.no_grad()
    def model_labels(self, x: np.ndarray | torch.Tensor, fg=None, tau: float | None = None,
                     settings: InferenceConfig | None = None, centres=None,
                     timings: dict | None = None) -> dict:
        """`segment_batch` up to the vote: the z-buffered (or label head's, or centre votes')
        labels, smoothed, with the renders and the reconstruction. `centres`, `timings`: as
        `segment_batch`'s. The z-buffer's labels are made before the centre votes are waited
        for: in this thread while the second one (`superpixel_thread`) makes them."""
        t0 = time.perf_counter()
        tau = self.tau if tau is None else float(tau)
        cfg = self.inference if settings is None else settings
        x = torch.as_tensor(x, dtype=torch.float32, device=self.device)
        out = infer(self.G, self.encoder(cfg.encoder_precision), x,
                    refine_steps=cfg.refine_steps, hypotheses=cfg.refine_hypotheses,
                    keep=cfg.refine_keep, swaps=cfg.refine_swaps)
        fg_t = (x[:, 0] > -1 + 1e-4) if fg is None else torch.as_tensor(fg, device=self.device)
        n = out["renders"].shape[1]
        t1 = time.perf_counter()
        # the z-buffer's labels need no centre votes: made while the second thread makes them
        labels = labels_from_renders(out["renders"], tau, fg_t)
        t_labels = time.perf_counter() - t1
        if cfg.centre_votes == "on":
            if isinstance(centres, Future):
                centres = centres.result()
            if centres is None:
                centres = self.centre_votes(x, fg_t, n, cfg.centre_precision, founding=True)
            if isinstance(centres, tuple):  # where a missed part may be split off: `founding`
                centres, out["founding"] = centres
        if timings is not None:  # the networks', and waiting for the second thread's
            timings["network"] = time.perf_counter() - t0 - t_labels
        if cfg.label_head == "on":
            if self.label_head is None:
                raise ValueError("label_head on: this model has no label head; valid: off")
            labels = head_labels(self.label_head, x, out["renders"], labels, fg_t)
        if cfg.centre_votes == "on":
            labels = match_to_renders(centres, labels, n)
        out["labels"] = smooth_labels(labels, x, out["renders"].shape[1], cfg.smooth)
        return out

    def vote_and_split(self, out: dict, x: np.ndarray | torch.Tensor,
                       settings: InferenceConfig | None = None, tau: float | None = None,
                       segments=None) -> dict:
        """`model_labels`' output -> a new dict with its labels voted within the depth
        superpixels and split (`settings.superpixel_scale`, `split_scale`; with centre votes a
        missed part is split off only where their heatmap puts a centre, `out["founding"]`),
        a wall's top unlabelled and instances too small to be a part in view merged
        (`superpixels.drop_walls`, `drop_small`), and each instance's score; `out`
        itself is left as it is, so that one frame's model labels can be voted at several
        scales (`vote_scale.choose`)."""
        tau = self.tau if tau is None else float(tau)
        cfg = self.inference if settings is None else settings
        x = torch.as_tensor(x, dtype=torch.float32, device=self.device)
        n = out["renders"].shape[1]
        if isinstance(segments, Future):
            segments = segments.result()
        labels = vote_labels(out["labels"], x, n, cfg.vote_scale, segments)
        labels, cut = split_labels(labels, x, n, cfg.split_scale, segments, out.get("founding"))
        labels = drop_small(drop_walls(labels))
        # a piece cut off another instance has no render to measure its visible share by: 0
        scores = instance_scores(out["renders"], labels, tau).masked_fill(cut, 0.0)
        return {**out, "labels": labels, "scores": scores}

    def __call__(self, depth_m: np.ndarray, prep_cfg=None, tau: float | None = None,
                 reconstruction: bool = True, settings: InferenceConfig | None = None,
                 timings: dict | None = None) -> Segmentation:
        """One depth frame (H, W) in metres -> Segmentation at the input's resolution.

        `prep_cfg` overrides the model's preprocessing (bin region, floor, min_height: the
        node's parameters); `tau` the calibrated threshold; `reconstruction=False` skips the
        metric re-rendered depth; `settings` the model's refinement and smoothing;
        `timings`, a dict, gets the seconds each stage took: "preprocess" (the frame to the
        model's input), "network" (the networks), "labels" (the rest).
        Raises ValueError on a bad frame."""
        t0 = time.perf_counter()
        prep_cfg = self.prep_cfg if prep_cfg is None else prep_cfg
        cfg = self.inference if settings is None else settings
        if prep_cfg.max_height != self.prep_cfg.max_height or prep_cfg.size != self.prep_cfg.size:
            raise ValueError("max_height and size are fixed by the model: "
                             f"{self.prep_cfg.max_height} m, {self.prep_cfg.size} px")
        prep = prepare(depth_m, prep_cfg)
        t1 = time.perf_counter()
        x, fg = prep.x[None, None], prep.fg[None]
        segments = centres = None
        if self.superpixel_thread and cfg.centre_votes == "on":  # first: needed first
            centres = self._in_second_thread(self.centre_votes, x, fg,
                                             self.model_cfg.n_instances, cfg.centre_precision,
                                             True)
        if self.superpixel_thread and (cfg.vote_scale > 0 or cfg.split_scale > 0):
            segments = self._in_second_thread(lambda: [frame_segments(
                prep.x, prep.fg, (cfg.vote_scale, cfg.split_scale))])
        stages = {} if timings is None else timings
        out = self.segment_batch(x, fg=fg, tau=tau, settings=cfg, segments=segments,
                                 centres=centres, timings=stages)
        labels64 = out["labels"][0].cpu().numpy()
        labels = extend_labels(labels_to_full(labels64, prep), depth_m, prep, prep_cfg)
        labels = smooth_full(labels, depth_m, prep.floor_depth, prep_cfg.max_height,
                             self.model_cfg.n_instances, cfg.smooth, prep_cfg.size, prep.roi)
        recon = None
        if reconstruction:
            recon64 = out["reconstruction"][0, 0].cpu().numpy()
            recon = self._heights_to_depth(recon64, prep, prep.shape)
        stages["preprocess"] = t1 - t0
        stages["labels"] = time.perf_counter() - t1 - stages["network"]
        return Segmentation(labels, recon, out["scores"][0].cpu().numpy(), labels64, prep.x,
                            prep.roi, prep.floor_depth, out["renders"][0].cpu().numpy(),
                            prep.fg, out["reconstruction"][0, 0].cpu().numpy())

    def _in_second_thread(self, fn, *args) -> Future:
        """`fn(*args)` in the one second thread (`superpixel_thread`), in order of submission."""
        if self._pool is None:
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="superpixels")
        return self._pool.submit(fn, *args)

    def _heights_to_depth(self, recon64: np.ndarray, prep, shape) -> np.ndarray:
        """Model output in [-1, 1] (64 x 64) -> metric depth at the input resolution (ROI only)."""
        x0, y0, x1, y1 = prep.roi
        h = (np.clip(recon64, -1, 1) + 1) / 2 * self.prep_cfg.max_height
        h = cv2.resize(h.astype(np.float32), (x1 - x0, y1 - y0), interpolation=cv2.INTER_LINEAR)
        out = np.zeros(shape, np.float32)
        out[y0:y1, x0:x1] = prep.floor_at(prep.roi) - h  # a tilted floor is a plane
        return out
