"""The shape loop: finish a model with labelled piles of the shape it learned.

A user has only unlabelled frames of their part. Once a model has learned the part's shape from
them (`inseggan train`), that shape becomes a simulator part (`sim.learned`), and piles of it,
seen through the user's camera with its noise, are scenes whose every label is known. The
encoder is then fitted to those labels (`distill --label-weight`), and the model shipped with a
card made from the user's own frames, without their labels (`modelcard.export_from_dataset`).
Without a model, the loop first learns the shape itself (`inseggan train` on the data set's
unlabelled frames), so one command goes from frames to a shipped model:

    inseggan loop --model runs/my_part/best.pt --data data/my_part --out runs/my_part_loop
    inseggan loop --data data/my_part --out runs/my_part_loop --train-minutes 40   # all of it
    inseggan loop --bag my_recording --instances 6 --out runs/my_part_loop --train-minutes 40
    inseggan loop --bag my_bolts --instances 5 --out runs/my_bolts_loop --match-piles \
        --iterations 0 --centre-iterations 3000 ...   # a head on a shaft: see stage 0c
    inseggan loop --bag my_blocks --instances 5 --out runs/my_blocks_loop --convex-pieces 1 \
        --iterations 0 --centre-iterations 3000 ...   # a box: see stage 0d

The user's frames are a simulated data set (`--data`: its meta.json names the camera, noise, bin
and instance count) or a recording (`--bag`, `BagFrames`: the camera and bin are estimated from
its depth frames and CameraInfo, `sim.user_camera`; the instance count and the sensor noise
preset are the user's to give). A bag's last `held_out` fraction of frames (in time order) is
kept out of everything but the card, as `inseggan export --bag` does; the piles of the learned
part are cut as the bag's frames are (the bin found in every frame, unless the model names a
region), so that the template meets them at the scale it was learned at.

Stages, each skipped when a killed run is started again and its result is there (the
simulation is written to a temporary folder and renamed when complete; the encoder's training
resumes from its last checkpoint; the export writes its folder atomically):
  0. shape (only without `--model`): `train.train` on the data set's training frames (no labels;
     validation by reconstruction when the data set has none) into out/shape, for the training
     config's budget; a killed run resumes from out/shape/last.pt; its best.pt is the model;
  0b. size (`size_by_thickness`; by default only for a rod the loop learned itself, and only
     an elongated one): a rod resized to the thickness the user's frames show (`sizing`)
     -> out/size/model.pt; not run on a folder whose piles were made without it
     (`resume_plan`);
  0c. match (only with `match_piles`, for a rod; then no size stage or rounds): the rod's
     radius profile cut into flat-ended discs (`shapefit.rod_discs`), its widest disc (a
     head, a flange) resized, and the whole stretched, over a grid, each variant piled in the
     user's bin and the one whose heights look most like the user's frames kept
     (`pilematch.search`; resumes variant by variant) -> out/match/best.pt. The piles are of
     that part; the model stays the rod, whose encoder and what follows learn from them (a
     CPU's rod of tilted bolts is two thirds of the bolt's length: docs/experiments.md,
     2026-12-02);
  0d. convex (only with `convex`, for a rod; then no size stage or rounds): the rod becomes a
     convex template (a box, a prism: flat faces, sharp edges), fitted with the rod's encoder
     and pose decoder to reconstruct the user's training frames and kept where it explains
     held-out frames best (`shapefit.fit_shape`, as `shape-fit` runs it) -> out/convex/best.pt,
     the model from then on (the wooden block: docs/experiments.md, 2026-12-04);
  1. simulate: `--scenes` labelled scenes of the learned part, with the camera, noise, bin and
     number of instances of the user's data set (its meta.json) or bag;
  2. encoder (not with `iterations` 0: the model's own encoder): the model's encoder fitted to
     them (`distill.DistillConfig` with the label losses), with `--user-weight`, while also
     reconstructing the user's own unlabelled training frames;
  2b. size rounds (`size_rounds`; by default AUTO_SIZE_ROUNDS for a rod the loop learned
     itself, none for a given model): the rod's scale chosen by how well it explains
     the user's frames (`sizing.choose_scale`; out/size_round<k>/scale.json); where it is not
     1, stages 1 and 2 again from the scaled model, into out/size_round<k>/sim and encoder;
     without an encoder stage (`iterations` 0) the rounds come before stage 1, which then
     simulates the last scale's piles once (the check never reads the piles);
  3. head (only with `head_iterations`): a label head (`label_head.py`) taught on the same
     piles to correct the z-buffer's labels; the model with it is out/head/model.pt;
  4. self (only with `self_frames`): the encoder fitted further to the model's own labels, at
     `self_settings`, of the user's training frames (`selffit.py`; no label read) ->
     out/self/last.pt;
  4b. centres (only with `centre_iterations`): centre votes (`centres.py`) taught on the same
     piles; the model with them (`centre_votes: on`) is out/centres/model.pt; or, with
     `centre_teacher` "self-labels", taught on the user's training frames labelled by the
     model itself (out/centres_self/model.pt), or with "pasted", on piles pasted from the
     parts seen whole in the user's training frames (`pasted.py`; out/centres_pasted/model.pt);
  5. export: out/model with the shipped settings (`export_settings`, realtime.yaml), the
     superpixel vote's scale chosen on the last piles' validation split (`vote_scales`,
     `vote_scale.py`: the piles' labels are the loop's own), tau and the card from the user's
     validation and test frames as if they had no labels (the test split's labels, where it
     has them, give the card's mIoU rows); for a bag, its frames before and after the
     held-out cut (labels from `labels_topic` only).
Writes out/summary.json with the time of each stage.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from inseggan_ros.evaluation.evaluate import write_json
from inseggan_ros.evaluation.vote_scale import SCALES as VOTE_SCALES
from inseggan_ros.evaluation.modelcard import markdown
from inseggan_ros.evaluation.verdict import verdict
from inseggan_ros.runtime.model import build_models
from inseggan_ros.learning.budget import DEFAULT_MINUTES, Budget
from inseggan_ros.learning.family import FITTED, FamilyConfig
from inseggan_ros.learning.piles import (  # noqa: F401  (the loop's frames and piles)
    BagFrames, _as_list, _model_file, _same_view, pile_scene, pile_view)

if TYPE_CHECKING:
    from inseggan_ros.learning.pilematch import PileMatchConfig
    from inseggan_ros.runtime.preprocess import PreprocessConfig
    from inseggan_ros.learning.shapefit import ShapeFitConfig


# the size rounds a loop that learns its own rod runs unless told otherwise (measured on two
# tilted recordings: docs/experiments.md, 2026-11-27)
AUTO_SIZE_ROUNDS = 2
# the shape stage's iterations where neither --train-iterations nor --train-minutes bound it:
# what every recording-made shipped model's recipe gives (config/recipes/*_tilted.yaml)
SHAPE_ITERATIONS = 600


@dataclass(frozen=True)
class LoopConfig:
    scenes: int = 3000  # labelled scenes of the learned part to train the encoder on
    val_scenes: int = 200  # and to choose its best checkpoint with
    min_instances: int | None = None  # each pile draws its count in min_instances..n (n: the
    # parts in the user's bin; 0: empty bins among them), as a robot that empties the bin sees
    # it, so that the centre votes learn to find the parts there are (None: every pile holds n)
    iterations: int = 0  # encoder iterations (0, the shipped models' recipe: no encoder stage,
    # the model's own encoder; then the piles teach what follows: centre votes or a label head)
    lr: float = 3e-4  # their learning rate (cosine schedule down to 0)
    label_weight: float = 1.0
    ownership_weight: float = 0.2
    user_weight: float = 0.0  # reconstruction of the user's own (unlabelled) training frames,
    # mixed into every encoder iteration (`DistillConfig.lambda_user`)
    user_frames: int = 3000  # at most this many of them
    head_iterations: int = 0  # of a label head on the same scenes (0 = none; it helped the
    # cone and hurt the pin connector: docs/experiments.md)
    centre_iterations: int = 3000  # of centre votes on the same scenes (`centres.py`; 0 = none;
    # on by default: every recording-made shipped model is made so)
    centre_teacher: str = "piles"  # what teaches them: "piles", the same scenes' labels; or
    # "self-labels", the user's training frames labelled by the model itself (no label read;
    # better where the learned part is not the real one: docs/experiments.md, 2026-11-29); or
    # "pasted", piles pasted from the parts seen whole in those frames (`pasted.py`; no
    # template: better where no family has the part's outline, docs/experiments.md, 2026-12-08)
    seed: int = 11  # of the simulated scenes
    workers: int = 1  # simulation processes (and self-labelling processes)
    name: str = "model"  # the exported model's name
    self_frames: int = 0  # of the user's training frames the encoder is then fitted to, with
    # the model's own labels of them (`selffit`; 0 = no such stage)
    self_iterations: int = 1500
    self_settings: str = "quality"  # the settings those labels are made with
    export_settings: str = "realtime"  # the shipped model's own settings (what the node and
    # the card use), over those of the checkpoint
    size_by_thickness: str = "auto"  # "on": a rod resized, before the first simulation, to
    # the thickness the user's frames show (`sizing.frame_thickness`); "auto": so only when the
    # loop learns the rod itself and it came out elongated (`sizing.ELONGATED`: a part lying on
    # its side, whose thickness is its width; a flat part's is not); "off"
    size_keep_length: bool = False  # the thickness rule scales the rod's radii only and keeps
    # its centres' span (`sizing.size_to_thickness`): for a long, thin part whose rod came out
    # thick (measured on tilted bolts: docs/experiments.md, 2026-11-28, afternoon)
    size_rounds: int | None = None  # after the encoder, up to this many rounds of: the rod's
    # scale chosen by how well it explains the user's frames (`sizing.choose_scale`), and where
    # it is not 1, the simulation and the encoder again at that scale (0 = none; None:
    # AUTO_SIZE_ROUNDS when the loop learns the rod itself, else 0)
    size_frames: int = 280  # of the user's frames for those two (not the card's)
    vote_scales: tuple[int, ...] = VOTE_SCALES  # at export, the superpixel vote's scale
    # chosen among these on the last simulated piles' validation split (`vote_scale.choose`;
    # () = the export settings' own scale)
    match_piles: PileMatchConfig | None = None  # stage 0c's grid (None: no such stage): the
    # piles are of a disc template cut from the rod, its head sized by how its piles look
    # (`pilematch`; its `workers` are the loop's)
    match_pieces: int = 2  # the discs of that template (2: a head on a shaft; 3: a flange)
    match_walls: int = 8  # the side planes of each disc
    convex: "ShapeFitConfig | None" = None  # stage 0d's fit (None: no such stage): the rod
    # becomes a convex template fitted to the user's frames by reconstruction (`shapefit`,
    # `shape-fit`'s default start: a box), and the piles are of it: flat faces and sharp edges
    # (the wooden block: docs/experiments.md, 2026-11-26 night and 2026-12-04)
    family: "FamilyConfig | None" = None  # stage 2c's candidates (None: no such stage): after
    # the rod is sized, the template family whose piles look most like the user's frames and
    # whose renders explain held-out frames best is kept (`family.choose`): the rod, a fitted
    # box or two boxes (the model becomes that convex template), or a T or an L of two bars,
    # discs, a ring or a taper, unfitted
    # (the model stays the rod, as with `match_piles`); the piles are of the kept one at the
    # scale whose piles look most like the frames. Only without an
    # encoder stage (`iterations` 0), for a rod, with neither `convex` nor `match_piles`
    minutes: float = DEFAULT_MINUTES  # the whole run's time budget (`budget.Budget`: the shape
    # stage, the family choice and the centre votes get their shares of it; 0 = none)

    def __post_init__(self):
        if self.self_frames < 0:
            raise ValueError(f"self_frames {self.self_frames!r} invalid; valid: >= 0 (0 = no "
                             "self-fitting stage)")
        if self.min_instances is not None and self.min_instances < 0:
            raise ValueError(f"min_instances {self.min_instances!r} invalid; valid: >= 0 (each "
                             "pile's count drawn in min_instances..n), or none (every pile n)")
        Budget(self.minutes)  # raises with what is valid
        for key in ("scenes", "val_scenes", "workers", "user_frames", "self_iterations"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key} {getattr(self, key)!r} invalid; valid: >= 1")
        if self.size_by_thickness not in ("auto", "on", "off"):
            raise ValueError(f"size_by_thickness {self.size_by_thickness!r} invalid; valid: "
                             "auto, on, off")
        if self.size_keep_length and self.size_by_thickness == "off":
            raise ValueError("size_keep_length without the thickness rule does nothing; valid: "
                             "size_by_thickness auto or on with it")
        if self.size_rounds is not None and self.size_rounds < 0:
            raise ValueError(f"size_rounds {self.size_rounds!r} invalid; valid: >= 0 (0 = the "
                             "template's size as learned)")
        if any(not isinstance(v, int) or v < 1 for v in self.vote_scales):
            raise ValueError(f"vote_scales {self.vote_scales!r} invalid; valid: integers >= 1, "
                             "or none (the export settings' own scale)")
        if self.size_frames < 20:
            raise ValueError(f"size_frames {self.size_frames!r} invalid; valid: >= 20")
        if self.head_iterations < 0:
            raise ValueError(f"head_iterations {self.head_iterations!r} invalid; valid: >= 0 "
                             "(0 = no label head)")
        if self.centre_iterations < 0 or 0 < self.centre_iterations < 4:
            raise ValueError(f"centre_iterations {self.centre_iterations!r} invalid; valid: "
                             "0 (no centre votes) or >= 4")
        if self.centre_teacher not in CENTRE_TEACHERS:
            raise ValueError(f"centre_teacher {self.centre_teacher!r} invalid; valid: "
                             f"{', '.join(CENTRE_TEACHERS)}")
        if self.centre_iterations and self.head_iterations:
            raise ValueError("head_iterations and centre_iterations both set: the labels come "
                             "from one of them; valid: at most one above 0")
        taught = self.centre_iterations or self.head_iterations
        if self.iterations < 0 or (self.iterations == 0 and not taught):
            raise ValueError(f"iterations {self.iterations!r} invalid; valid: >= 1, or 0 (no "
                             "encoder stage) with centre_iterations or head_iterations, which "
                             "then learn from the piles")
        if self.match_piles is not None:
            from inseggan_ros.learning.shapefit import ShapeFitConfig

            ShapeFitConfig(pieces=self.match_pieces, walls=self.match_walls, iterations=0,
                           start="discs", taper=min(self.match_piles.tapers))  # raises with
            # what is wrong (a taper of more than one disc)
        if self.convex is not None and self.match_piles is not None:
            raise ValueError("convex and match_piles both set: the piles are of one template, "
                             "the fitted convex one or the matched discs; valid: at most one")
        if self.family is not None and (self.convex is not None or self.match_piles is not None
                                        or self.iterations):
            raise ValueError("family (the template family chosen by the frames) with convex, "
                             "match_piles or an encoder stage: the template is named, or the "
                             "piles come after the encoder; valid: family alone, with "
                             "iterations 0")
        if not 0 < self.lr < 1:
            raise ValueError(f"lr {self.lr!r} invalid; valid: in (0, 1)")
        if not self.user_weight >= 0:
            raise ValueError(f"user_weight {self.user_weight!r} invalid; valid: >= 0")


def bag_shape_frames(data: BagFrames, val_frames: int = 100
                     ) -> tuple[dict, dict, PreprocessConfig, dict]:
    """A recording's frames as the shape is learned from them, the bin found in every frame as
    `inseggan train --bag` finds it -> (training frames: all before the held-out cut; the first
    `val_frames` held-out ones, validated on without labels; the preprocessing; the data record
    the checkpoint keeps, with the camera that sizes the template in metres)."""
    from inseggan_ros.data.datasets import bag_view
    from inseggan_ros.runtime.preprocess import PreprocessConfig
    from inseggan_ros.sim.user_camera import camera_from_bag

    prep = PreprocessConfig()
    frames, val = data.frames(prep)
    val = {k: (v[:val_frames] if isinstance(v, np.ndarray) else v) for k, v in val.items()
           if k != "labels"}  # the labels topic is the card's only: validation without
    info = {"source": "bag", "path": str(data.path), "topic": data.topic,
            "train_frames": len(frames["x"]), "val_frames": len(val["x"]),
            "camera": asdict(camera_from_bag(data.path, data.topic)[0]),
            "view": bag_view(frames)}
    return frames, val, prep, info


def learn_shape(data, out, train_cfg, progress: bool = True, val_frames: int = 100) -> Path:
    """Stage 0: learn the part's shape from the user's unlabelled training frames with
    `train_cfg` (a `train.TrainConfig`; its instance count is the data set's) -> out/best.pt.
    Skipped when out/summary.json says the run finished; resumed from out/last.pt after a kill."""
    from inseggan_ros.data.datasets import load_sim_training
    from inseggan_ros.learning.train import train

    out = Path(out)
    if (out / "summary.json").is_file() and (out / "best.pt").is_file():
        return out / "best.pt"
    if isinstance(data, BagFrames):
        n = data.instances
        frames, val, prep, info = bag_shape_frames(data, val_frames)
    else:
        frames, val, prep, info = load_sim_training(data, val_frames=val_frames,
                                                    progress=progress)
        n = info["instances"]
    train_cfg = replace(train_cfg, model=replace(train_cfg.model, n_instances=n))
    frames.pop("labels", None)  # the shape is learned without labels
    train(train_cfg, frames, val, out, prep.to_dict(), info, resume=(out / "last.pt").is_file(),
          progress=progress)
    return out / "best.pt"


def label_head_stage(model: Path, sim: Path, data, out: Path, cfg: LoopConfig,
                     progress: bool = True) -> Path:
    """Stage 3: a label head (`label_head.fit`) for the encoder's model on the simulated piles,
    at the tau the user's validation frames give without their labels (as the export will
    calibrate it) -> out/model.pt. Skipped when that exists."""
    from inseggan_ros.learning.label_head import HeadConfig, fit
    from inseggan_ros.runtime.segment import Segmenter
    from inseggan_ros.evaluation.selfcheck import calibrate

    if (out / "model.pt").is_file():
        return out / "model.pt"
    seg = Segmenter.from_checkpoint(model, device="cpu")
    calib = _user_frames(data, seg.prep_cfg, "val", 200)  # the 200 the export calibrates on
    tau, _ = calibrate(seg, calib["x"], calib["fg"])
    hcfg = HeadConfig(iterations=cfg.head_iterations, seed=cfg.seed,
                      eval_every=max(1, min(250, cfg.head_iterations)))
    return Path(fit(model, sim, out, hcfg, tau=tau, progress=progress,
                    as_given=isinstance(data, BagFrames))["model"])


# what may teach the loop's centre votes (`LoopConfig.centre_teacher`) -> its stage's folder
CENTRE_TEACHERS = {"piles": "centres", "self-labels": "centres_self", "pasted": "centres_pasted"}


def centres_stage(model: Path, sim: Path, view: dict, data, out: Path, cfg: LoopConfig,
                  progress: bool = True, budget: Budget | None = None) -> Path:
    """Stage 4b: centre votes (`centres.fit`) for the model on the last simulated piles, cut
    as the user's frames are (`view`), or with `cfg.centre_teacher` "self-labels" on the user's
    training frames (a data set's train split, a bag's frames before the held-out cut)
    labelled by the model itself, the last fifth of them (at most 200) kept to choose by, or
    with "pasted" on piles pasted from the parts seen whole in those frames (`pasted.py`) ->
    out/model.pt. A killed run resumes from out/last.pt; skipped when out/model.pt exists."""
    from inseggan_ros.learning.centres import CentreConfig, fit

    if (out / "model.pt").is_file():
        return out / "model.pt"
    iterations = _centre_iterations(cfg, out, budget)
    ccfg = CentreConfig(iterations=iterations, seed=cfg.seed,
                        eval_every=max(1, min(500, iterations)))
    if cfg.centre_teacher == "piles":
        return Path(fit(model, sim, out, ccfg, progress=progress,
                        as_given=view.get("as_given", False))["model"])
    from inseggan_ros.runtime.segment import Segmenter

    prep = Segmenter.from_checkpoint(model, device="cpu").prep_cfg
    frames = _user_frames(data, prep, "train", None, progress)
    source = data.path if isinstance(data, BagFrames) else data
    if cfg.centre_teacher == "pasted":
        from inseggan_ros.learning.pasted import PasteConfig

        return Path(fit(model, source, out, ccfg, progress=progress, user_frames=frames,
                        pasted=PasteConfig(seed=cfg.seed, train=cfg.scenes,
                                           val=cfg.val_scenes))["model"])
    held_out = max(1, min(200, len(frames["x"]) // 5))
    return Path(fit(model, source, out, ccfg, progress=progress, self_labels=True,
                    held_out=held_out, workers=cfg.workers, user_frames=frames)["model"])


def _centre_iterations(cfg: LoopConfig, out: Path, budget: Budget | None) -> int:
    """The centre votes' iterations: `cfg.centre_iterations`, or fewer where the budget's share
    does not hold them at the seconds an iteration takes here (`centres.step_seconds`). Chosen
    once and kept in out/budget.json, so that a killed stage resumes the same schedule."""
    from inseggan_ros.learning import budget as budget_mod
    from inseggan_ros.learning.centres import CentreConfig, step_seconds

    kept = out / "budget.json"
    if kept.is_file():
        iterations = json.loads(kept.read_text())["iterations"]
    elif budget is None or not budget.bounded:
        return cfg.centre_iterations
    else:
        seconds = budget.share("centres")
        step = step_seconds(CentreConfig(seed=cfg.seed))
        iterations = budget_mod.centre_iterations(cfg.centre_iterations, seconds, step)
        out.mkdir(parents=True, exist_ok=True)
        write_json(kept, {"iterations": iterations, "asked": cfg.centre_iterations,
                          "share_s": seconds, "step_s": step})
    if budget is not None and iterations < cfg.centre_iterations:
        budget.cut(f"centre votes: {iterations} of {cfg.centre_iterations} iterations")
    return iterations


def self_stage(model: Path, data, out: Path, cfg: LoopConfig, progress: bool = True) -> Path:
    """Stage 4: `selffit.self_fit` of the model on `cfg.self_frames` of the user's training
    frames (the first of a data set's train split, or a bag's spread evenly over its frames
    before the held-out cut: a recording's neighbouring frames are alike), cut as the model
    cuts them, tau from the 200 frames the export calibrates on -> out/last.pt."""
    from inseggan_ros.runtime.segment import Segmenter
    from inseggan_ros.learning.selffit import SelfFitConfig, self_fit

    prep = Segmenter.from_checkpoint(model, device="cpu").prep_cfg
    calib = _user_frames(data, prep, "val", 200)  # the 200 the export calibrates on
    frames = _user_frames(data, prep, "train", cfg.self_frames, progress)
    scfg = SelfFitConfig(frames=cfg.self_frames, iterations=cfg.self_iterations,
                         settings=cfg.self_settings, lr=cfg.lr, label_weight=cfg.label_weight,
                         ownership_weight=cfg.ownership_weight, workers=cfg.workers,
                         seed=cfg.seed)
    return self_fit(model, frames, calib, out, scfg, progress)


def _shipped_segmenter(file: Path, cfg: LoopConfig):
    """The Segmenter of `file` with `cfg.export_settings` over its checkpoint's (a training
    checkpoint carries only the bare defaults), as the exported model will run."""
    from inseggan_ros.core import settings
    from inseggan_ros.runtime.segment import Segmenter

    seg = Segmenter.from_checkpoint(file, device="cpu")
    seg.inference = settings.apply_file(seg.inference, cfg.export_settings, seg.stored_settings)
    return seg


def _export(finished: Path, data, cfg: LoopConfig, out: Path, piles: dict | None = None,
            camera=None, recipe: dict | None = None) -> dict:
    """Stage 5: the model shipped with `cfg.export_settings` (a training checkpoint carries
    only the bare defaults: no refinement, one starting point, no smoothing); with labelled
    `piles` (the last simulation's validation split; `run` loads them only where
    `cfg.vote_scales` names scales), the vote's scale chosen on them among those. `camera`:
    the one the template was learned through (`sim.learned.model_camera` of the loop's
    model), recorded where the checkpoint lacks it. `recipe`: the run's resolved
    configuration, for the card."""
    from inseggan_ros.evaluation.modelcard import export_from_bag, export_from_dataset

    inference = _shipped_segmenter(finished, cfg).inference
    if isinstance(data, BagFrames):
        return export_from_bag(finished, data.path, cfg.name, out, data.topic, data.labels_topic,
                               data.held_out, inference=inference, vote_piles=piles,
                               vote_scales=cfg.vote_scales, camera=camera, recipe=recipe)
    return export_from_dataset(finished, data, cfg.name, out, inference=inference,
                               vote_piles=piles, vote_scales=cfg.vote_scales, camera=camera,
                               recipe=recipe)


def run_self_fit(model, data, out, cfg: LoopConfig, progress: bool = True) -> dict:
    """Stage 4 alone, for a finished model (`inseggan self-fit`): out/last.pt, then exported
    as stage 5 exports, to out/model -> summary (also out/self_fit.json)."""
    from inseggan_ros.learning.selffit import check_settings

    if not cfg.self_frames:
        raise ValueError("self_frames 0 invalid; valid: >= 1 (the frames to fit to)")
    file = _model_file(model).resolve()
    check_settings(cfg.self_settings)
    check_settings(cfg.export_settings)
    if isinstance(data, BagFrames):
        from inseggan_ros.core.paths import resolve_bag

        resolve_bag(str(data.path), "--bag")
    else:
        _same_view(file, data)
    out = Path(out)
    t0 = time.monotonic()
    finished = self_stage(file, data, out, cfg, progress)
    seconds = {"self": round(time.monotonic() - t0, 1)}
    t0 = time.monotonic()
    card = _export(finished, data, cfg, out / "model")
    seconds["export"] = round(time.monotonic() - t0, 1)
    summary = {"model": str(model), "config": asdict(cfg), "seconds": seconds,
               "data": str(data) if not isinstance(data, BagFrames) else data.describe(),
               "encoder": json.loads((out / "summary.json").read_text()),
               "card": str(out / "model" / "card.json"), "tau": card.get("tau")}
    write_json(out / "self_fit.json", summary)
    return summary


def _simulate_and_fit(file: Path, data, meta: dict | None, view: dict, sim: Path,
                      encoder: Path, cfg: LoopConfig, seconds: dict, tag: str,
                      progress: bool, part: Path | None = None) -> Path:
    """Stages 1 and 2 for the template of `file`: `cfg.scenes` labelled piles of it (or of the
    model `part`, stage 0c's) into `sim`, then its encoder fitted to them into `encoder` ->
    encoder/best.pt (`file` itself with `cfg.iterations` 0). Each is skipped when its result
    is complete (`meta` None: the user's frames are a bag, `data`)."""
    from inseggan_ros.data import datasets as data_mod
    from inseggan_ros.learning.distill import DistillConfig, distill
    from inseggan_ros.sim.dataset import DatasetSpec, generate

    t0 = time.monotonic()
    if not (sim / "meta.json").is_file():
        scene = pile_scene(data, meta, part or file)
        if cfg.min_instances is not None:
            scene = replace(scene, min_instances=min(cfg.min_instances, scene.instances))
        spec = DatasetSpec(scene, {"train": cfg.scenes, "val": cfg.val_scenes, "test": 0},
                           seed=cfg.seed)
        generate(spec, sim, workers=cfg.workers, progress=progress)
    seconds["simulate" + tag] = round(time.monotonic() - t0, 1)
    if not cfg.iterations:
        return file

    t0 = time.monotonic()
    if not (encoder / "summary.json").is_file():
        train = data_mod.load_sim_split(sim, "train", progress=progress, **view)
        val = data_mod.load_sim_split(sim, "val", limit=100, **view)
        dcfg = DistillConfig(frames=cfg.scenes, iterations=cfg.iterations, lr=cfg.lr,
                             lr_schedule="cosine",
                             eval_every=max(1, min(500, cfg.iterations)), lambda_pose=0.0,
                             lambda_label=cfg.label_weight,
                             lambda_ownership=cfg.ownership_weight,
                             lambda_user=cfg.user_weight, seed=cfg.seed)
        user = None  # the user's frames, not their labels
        if cfg.user_weight > 0:
            user = (data_mod.load_sim_split(data, "train", limit=cfg.user_frames,
                                            progress=progress)["x"] if meta is not None
                    else data.frames(view["cfg"])[0]["x"][:cfg.user_frames])
        distill(file, train["x"], val, encoder, dcfg, resume=True, progress=progress,
                train_labels=train["labels"], user_x=user)
    seconds["encoder" + tag] = round(time.monotonic() - t0, 1)
    return encoder / "best.pt"


def _user_frames(data, prep, split: str, limit: int | None, progress: bool = False) -> dict:
    """Up to `limit` (None: all) of the user's frames that are not the card's: a bag's frames
    before its held-out cut, spread evenly over them, or the first of a data set's `split`."""
    from inseggan_ros.data import datasets as data_mod

    if isinstance(data, BagFrames):
        return data.frames(prep, limit=limit)[0]
    return data_mod.load_sim_split(data, split, prep, limit=limit, progress=progress)


def size_plan(cfg: LoopConfig, learns: bool, renderer: str) -> tuple[str, int]:
    """What the loop sizes: ("on" | "if_elongated" | "off", size rounds) from the config, whether
    the loop learns the template itself (`learns`) and its renderer. By default ("auto", None) a
    rod the loop learns itself is sized, to the thickness only if it is elongated, and gets
    AUTO_SIZE_ROUNDS rounds; a given model is left as it is. Asking for either on a template
    that is not a rod, or for `size_keep_length` where the thickness rule is off, raises,
    before any stage spends its time."""
    rod = renderer == "spheres"
    if cfg.convex is not None:
        if not rod:
            raise ValueError(f"--convex-pieces fits a convex template from a rod of spheres; "
                             f"the model's template is {renderer!r} (valid: a rod model, or "
                             "without --convex-pieces)")
        rod = False  # what is sized is the fitted template, not the rod
    if cfg.match_piles is not None:
        if not rod:
            raise ValueError(f"--match-piles cuts a rod of spheres into discs; the model's "
                             f"template is {renderer!r} (valid: a rod model, or without "
                             "--match-piles)")
        if cfg.size_by_thickness == "on" or cfg.size_rounds or cfg.size_keep_length:
            raise ValueError("--match-piles sizes the part itself (its head, its length); "
                             "valid: without --size-by-thickness on, --size-keep-length and "
                             "--size-rounds")
        return "off", 0
    if not rod and (cfg.size_by_thickness == "on" or cfg.size_rounds):
        raise ValueError(f"--size-by-thickness / --size-rounds size a rod of spheres; the "
                         f"model's template is {renderer!r} (valid: renderer 'spheres', or "
                         "--size-by-thickness off --size-rounds 0)")
    auto = learns and rod
    thickness = cfg.size_by_thickness
    if thickness == "auto":
        thickness = "if_elongated" if auto else "off"
    if cfg.size_keep_length and thickness == "off":
        raise ValueError("--size-keep-length changes the thickness rule, which is off here "
                         "(--size-by-thickness auto sizes only a rod the loop learns itself, "
                         "not a given --model or a template that is not a rod); valid: "
                         "--size-by-thickness on with it for a rod, or leave it out")
    rounds = cfg.size_rounds
    if rounds is None:
        rounds = AUTO_SIZE_ROUNDS if auto else 0
    return thickness, rounds


def unsized_before(out: Path) -> bool:
    """Whether the loop folder `out` already holds piles or an encoder made without the size
    stage (a run of a version, or of settings, that did not size): sizing its rod now would
    leave them of the unsized part."""
    out = Path(out)
    made = (out / "sim" / "meta.json").is_file() or (out / "encoder").is_dir()
    return made and not (out / "size" / "size.json").is_file()


def resume_plan(thickness: str, out: Path) -> str:
    """The size stage's plan (`size_plan`) for the loop folder `out`: as planned, unless `out`
    already holds stages made without it (`unsized_before`). Then the default plan is dropped
    (the run goes on as it was started; the scale rounds, which come after the piles, still
    run), and a stage asked for ("on") raises before any stage."""
    if thickness == "off" or not unsized_before(out):
        return thickness
    if thickness == "on":
        raise ValueError(f"{out} holds piles or an encoder made without the size stage (sim/ "
                         "or encoder/, no size/size.json): sizing the rod now would leave them "
                         "of the unsized part; give a new --out, or resume this one with "
                         "--size-by-thickness off")
    return "off"


def size_stage(file: Path, data, out: Path, cfg: LoopConfig, only_elongated: bool = False
               ) -> Path:
    """Stage 0b: the rod of `file` resized to the thickness of the parts in the user's frames
    (`sizing.frame_thickness` on a bag's frames before its cut, or a data set's training
    split; no label read) -> out/model.pt, with out/size.json. With `only_elongated`, a rod
    shorter than `sizing.ELONGATED` times its width is left as it is (size.json says so, and
    `file` is returned). Skipped when done."""
    from inseggan_ros.core import checkpoint
    from inseggan_ros.learning import sizing
    from inseggan_ros.runtime.preprocess import PreprocessConfig
    from inseggan_ros.sim.learned import model_camera, template_scale

    if (out / "size.json").is_file():
        done = json.loads((out / "size.json").read_text())
        if done.get("left_as_is"):
            return file
        if (out / "model.pt").is_file():
            return out / "model.pt"
    state = checkpoint.load(file)
    G = build_models(state, file)[1]
    prep = PreprocessConfig.from_dict(state["preprocess_config"])
    camera = model_camera(file, state)
    metres = template_scale(state, G, camera)
    before = sizing.rod_dimensions_mm(G, metres)
    if only_elongated and not sizing.elongated(before):
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "size.json", {
            "model": str(file), "left_as_is": f"the rod is not elongated (length / width "
            f"{before[0] / before[1]:.2f} < {sizing.ELONGATED}): its thickness need not be its "
            "width", "dimensions_mm_before": before, "dimensions_mm_after": before})
        return file
    frames = _user_frames(data, prep, "train", cfg.size_frames)
    if len(frames["x"]) == 0 and not isinstance(data, BagFrames):  # a data set of no training
        frames = _user_frames(data, prep, "val", cfg.size_frames)  # split: its validation one
    thickness = sizing.frame_thickness(frames["x"], frames["fg"], prep.max_height)
    s = sizing.size_to_thickness(state, G, float(metres[2]), thickness, cfg.size_keep_length)
    G = build_models(state, file)[1]
    after = sizing.rod_dimensions_mm(G, template_scale(state, G, camera))
    out.mkdir(parents=True, exist_ok=True)
    checkpoint.save(out / "model.pt", state)
    write_json(out / "size.json", {
        "model": str(file), "frames": int(len(frames["x"])), "thickness_mm": thickness * 1000,
        "scale": s, "keep_length": cfg.size_keep_length,
        "spheres": int(state["model_config"]["spheres"]),
        "dimensions_mm_before": before, "dimensions_mm_after": after})
    return out / "model.pt"


def match_stage(file: Path, data, out: Path, cfg: LoopConfig, progress: bool = True) -> Path:
    """Stage 0c: the part the piles are made of, a disc template cut from the rod of `file`
    (`cfg.match_pieces` discs of `cfg.match_walls` sides), its widest disc sized and the whole
    stretched over `cfg.match_piles`' grid by how the piles of each variant look against the
    user's training frames (`pilematch.search`, into out/search; no label read), then written
    as `shape-fit --start discs --iterations 0 --match-piles` writes it (`shapefit.fit_shape`,
    its reconstruction of held-out frames measured, not fitted) -> out/best.pt. A killed
    search resumes from the variants it measured; each step is skipped when done."""
    from inseggan_ros.core import checkpoint
    from inseggan_ros.learning.pilematch import search
    from inseggan_ros.runtime.preprocess import PreprocessConfig
    from inseggan_ros.learning.shapefit import ShapeFitConfig, fit_shape, hold_out

    if (out / "summary.json").is_file() and (out / "best.pt").is_file():
        return out / "best.pt"
    shape_cfg = ShapeFitConfig(pieces=cfg.match_pieces, walls=cfg.match_walls, iterations=0,
                               start="discs")
    prep = PreprocessConfig.from_dict(checkpoint.load(file)["preprocess_config"])
    if isinstance(data, BagFrames):  # the frames `shape-fit --bag` fits and validates on
        x, val = hold_out(data.frames(prep)[0]["x"], shape_cfg)
    else:
        x = _user_frames(data, prep, "train", shape_cfg.frames, progress)["x"]
        val = _user_frames(data, prep, "val", shape_cfg.val_frames)["x"]
    m = search(file, shape_cfg, data, x, out / "search",
               replace(cfg.match_piles, workers=cfg.workers), progress)
    return Path(fit_shape(file, x, out, replace(shape_cfg, hole=m.get("hole", 0.0),
                                                taper=m.get("taper", 1.0)),
                          val_x=val, progress=progress, discs=m["discs"])["model"])


def convex_stage(file: Path, data, out: Path, cfg: LoopConfig, progress: bool = True) -> Path:
    """Stage 0d: the rod of `file` becomes a convex template (`cfg.convex`: its pieces and
    walls), fitted with the rod's encoder and pose decoder to reconstruct the user's training
    frames and kept where it reconstructs held-out frames best, as `shape-fit` does
    (`shapefit.fit_shape`; no label read) -> out/best.pt. Resumes from out/last.pt."""
    from inseggan_ros.core import checkpoint
    from inseggan_ros.runtime.preprocess import PreprocessConfig
    from inseggan_ros.learning.shapefit import fit_shape, hold_out

    prep = PreprocessConfig.from_dict(checkpoint.load(file)["preprocess_config"])
    if isinstance(data, BagFrames):  # the frames `shape-fit --bag` fits and validates on
        x, val = hold_out(data.frames(prep)[0]["x"], cfg.convex)
    else:
        x = _user_frames(data, prep, "train", cfg.convex.frames, progress)["x"]
        val = _user_frames(data, prep, "val", cfg.convex.val_frames)["x"]
    return Path(fit_shape(file, x, out, cfg.convex, val_x=val, progress=progress)["model"])


def scale_check(file: Path, data, out: Path, cfg: LoopConfig) -> dict:
    """Stage 2b: the scale of the rod of `file`, at the settings it will ship with, that
    explains the user's frames best (`sizing.choose_scale`: tau calibrated on some of them,
    the error measured on others, none of them the card's; no label read) -> out/scale.json;
    where the scale is not 1, out/start.pt is `file` at that scale. Skipped when done."""
    from inseggan_ros.core import checkpoint
    from inseggan_ros.learning import sizing

    if (out / "scale.json").is_file():
        return json.loads((out / "scale.json").read_text())
    seg = _shipped_segmenter(file, cfg)
    frames = _user_frames(data, seg.prep_cfg, "val", cfg.size_frames)
    held = max(1, len(frames["x"]) * 2 // 7)  # 80 of 280
    calib = {k: frames[k][:-held] for k in ("x", "fg")}
    test = {k: frames[k][-held:] for k in ("x", "fg")}
    scale, rows = sizing.choose_scale(seg, calib, test)
    chosen = {"model": str(file), "scale": scale, "calibration_frames": len(calib["x"]),
              "held_out_frames": held, "rows": rows}
    out.mkdir(parents=True, exist_ok=True)
    if scale != 1.0:
        state = checkpoint.load(file)
        sizing.scale_state(state, scale)
        checkpoint.save(out / "start.pt", state)
        chosen["start"] = str(out / "start.pt")
    write_json(out / "scale.json", chosen)
    return chosen


def run(model, data, out, cfg: LoopConfig = LoopConfig(), progress: bool = True,
        train_cfg=None, recipe: dict | None = None) -> dict:
    """The loop for `model` (its learned template) and the user's frames `data` (a data set's
    folder, or `BagFrames`) -> summary (also out/summary.json). With `model` None the shape is
    learned first with `train_cfg`. `recipe`: the run's resolved configuration (`inseggan
    loop`'s options, with `command` and `commit`), written as out/recipe.yaml (atomically)
    once the run is known to start, and stored on the model's card."""
    from inseggan_ros.core import checkpoint
    from inseggan_ros.core import recipe as recipe_file
    from inseggan_ros.sim.learned import model_camera

    meta, planned, thickness, size_rounds = _check(model, data, out, cfg, train_cfg)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)  # drops the default stage for an unsized folder
    if recipe is not None:
        recipe_file.write(out / "recipe.yaml", recipe, RECIPE_HEADER)
    seconds: dict[str, float] = {}
    stages = tqdm(total=(2 if model is not None else 3) + bool(cfg.iterations)
                  + bool(cfg.head_iterations) + (cfg.match_piles is not None)
                  + (cfg.convex is not None) + (cfg.family is not None)
                  + bool(cfg.self_frames) + bool(cfg.centre_iterations)
                  + (thickness != "off") + size_rounds,
                  desc="loop", unit="stage", disable=not progress,
                  position=0)
    tick = _stage_timer(seconds, stages, _budget(cfg, model is None))
    if model is None:
        train_cfg = _shape_budget(train_cfg, tick.budget)
        model = tick("shape", learn_shape, data, out / "shape", train_cfg, progress)
        _shape_cut(out / "shape", train_cfg, tick.budget)
    file = _model_file(model).resolve()
    if meta is not None:
        _same_view(file, data)
    state = checkpoint.load(file)
    view = pile_view(data, state)
    camera = model_camera(file, state)  # its template's size: the model folder's card names it

    file, part = _template_stages(file, data, out, cfg, thickness, tick, progress)
    if cfg.iterations:
        sim, encoder = out / "sim", out / "encoder"
        finished = _simulate_and_fit(file, data, meta, view, sim, encoder, cfg, seconds, "",
                                     progress, part)
        stages.update(1 + bool(cfg.iterations))
        finished, sim, encoder, rounds = _size_rounds(finished, data, meta, view, out, cfg,
                                                      size_rounds, tick, stages, progress)
    else:
        finished, sim, encoder, rounds = _scale_then_simulate(
            file, data, meta, view, out, cfg, size_rounds, tick, stages, progress, part)
    finished = _finishing_stages(finished, sim, view, data, out, cfg, tick, progress)
    card = tick("export", _export_stage, finished, sim, view, data, cfg, out, camera, recipe,
                tick.budget)
    stages.close()

    summary = {"model": str(model), "data": str(data) if meta is not None else data.describe(),
               "config": asdict(cfg),
               "seconds": seconds, "encoder": (json.loads((encoder / "summary.json").read_text())
                                               if cfg.iterations else None),
               "card": str(out / "model" / "card.json"), "tau": card.get("tau"),
               "vote_scale": card.get("vote_scale"), "verdict": card["verdict"],
               "budget": card["budget"]}
    _summarise_templates(summary, out, planned, thickness, size_rounds, rounds, part)
    if card.get("template_family"):
        summary["template_family"] = card["template_family"]
    write_json(out / "summary.json", summary)
    return summary


RECIPE_HEADER = ("inseggan loop: this run's configuration, every option after defaults (the "
                 "flags' names,\nwith underscores). `inseggan loop --recipe recipe.yaml` runs it "
                 "again; flags given\nbeside --recipe override its values.")


def _check(model, data, out, cfg: LoopConfig, train_cfg) -> tuple:
    """What the loop refuses, before any stage spends its time: a missing model, frames or
    settings file, a sizing plan its template cannot take -> (the data set's meta.json, None
    for a bag; the size stage planned; as it runs in `out`; the size rounds)."""
    from inseggan_ros.core import checkpoint
    from inseggan_ros.learning.selffit import check_settings
    from inseggan_ros.sim.dataset import load_meta

    if (model is None) == (train_cfg is None):
        raise ValueError("give a trained model, or a training config to learn the shape with "
                         "(not both)")
    if model is not None:
        _model_file(model)  # a missing model is named before anything else
    renderer = (train_cfg.model.renderer if model is None else checkpoint.load(
        _model_file(model))["model_config"].get("renderer", "learned"))
    thickness, size_rounds = size_plan(cfg, model is None, renderer)  # raises before any stage
    check_settings(cfg.export_settings)
    if cfg.self_frames:
        check_settings(cfg.self_settings)
    meta = None  # a data set's meta.json (None: the frames are a bag's)
    if not isinstance(data, BagFrames):
        meta = load_meta(data)  # raises with what is wrong
    else:
        from inseggan_ros.core.paths import resolve_bag

        resolve_bag(str(data.path), "--bag")  # a missing bag is named before anything else
    return meta, thickness, resume_plan(thickness, Path(out)), size_rounds


def _budget(cfg: LoopConfig, learns: bool) -> Budget:
    """The run's time budget, over the stages it has (`budget.ORDER`)."""
    return Budget(cfg.minutes, tuple(
        s for s, on in (("shape", learns), ("family", cfg.family is not None), ("simulate", True),
                        ("centres", bool(cfg.centre_iterations)), ("export", True)) if on))


def _shape_budget(train_cfg, budget: Budget):
    """The shape stage's config with its share of the budget as its wall-clock limit (where
    that is tighter than its own)."""
    limit = budget.share("shape") / 60
    if math.isfinite(limit) and not 0 < train_cfg.max_minutes <= limit:
        return replace(train_cfg, max_minutes=round(max(limit, 0.5), 2))
    return train_cfg


def _shape_cut(folder: Path, train_cfg, budget: Budget) -> None:
    """Where the shape stage stopped on its time limit before its iterations: said so."""
    done = json.loads((folder / "summary.json").read_text())["iterations"]
    if budget.bounded and done < train_cfg.max_iterations:
        budget.cut(f"shape stage: {done} of {train_cfg.max_iterations} iterations in its "
                   f"{train_cfg.max_minutes:g} min")


def _stage_timer(seconds: dict, stages, budget: Budget):
    """tick(name, stage, *args): runs `stage(*args)`, records its seconds under `name` and
    advances the progress bar by one stage -> the stage's result. `tick.budget` is the run's
    time budget."""
    def tick(name: str, stage, *args):
        t0 = time.monotonic()
        result = stage(*args)
        seconds[name] = round(time.monotonic() - t0, 1)
        stages.update(1)
        return result

    tick.seconds = seconds  # for the stages that record their own (`_simulate_and_fit`)
    tick.budget = budget
    return tick


def _template_stages(file: Path, data, out: Path, cfg: LoopConfig, thickness: str, tick,
                     progress: bool) -> tuple[Path, Path | None]:
    """Stages 0d (convex), 0b (size) and 0c (match), those asked for -> (the model from then
    on, the piles' part where it is not the model's template: stage 0c's discs)."""
    if cfg.convex is not None:
        file = tick("convex", convex_stage, file, data, out / "convex", cfg, progress)
    if thickness != "off":
        file = tick("size", size_stage, file, data, out / "size", cfg,
                    thickness == "if_elongated")
    part = None
    if cfg.match_piles is not None:
        part = tick("match", match_stage, file, data, out / "match", cfg, progress)
    return file, part


def _size_rounds(finished: Path, data, meta, view: dict, out: Path, cfg: LoopConfig,
                 size_rounds: int, tick, stages, progress: bool) -> tuple:
    """Stage 2b, up to `size_rounds` rounds: the scale chosen; where it is not 1, stages 1 and
    2 again from the scaled model -> (the model, its piles, its encoder folder, each round's
    choice)."""
    sim, encoder, rounds = out / "sim", out / "encoder", []
    for k in range(1, size_rounds + 1):
        chosen = tick(f"scale{k}", scale_check, finished, data, out / f"size_round{k}", cfg)
        rounds.append(chosen)
        if chosen["scale"] == 1.0:
            break
        stages.total += 1 + bool(cfg.iterations)
        sim, encoder = out / f"size_round{k}" / "sim", out / f"size_round{k}" / "encoder"
        finished = _simulate_and_fit(Path(chosen["start"]), data, meta, view, sim, encoder,
                                     cfg, tick.seconds, str(k), progress)
        stages.update(1 + bool(cfg.iterations))
    return finished, sim, encoder, rounds


def _scale_then_simulate(file: Path, data, meta, view: dict, out: Path, cfg: LoopConfig,
                         size_rounds: int, tick, stages, progress: bool,
                         part: Path | None) -> tuple:
    """Stage 2b before stage 1, where there is no encoder stage (`iterations` 0): the scale
    check reads the model's own encoder and template only, never the piles, so the rounds
    choose their scales first and the piles are simulated once, of the last scale, into the
    folder the rounds' order gives it (out/sim, or out/size_round<k>/sim for the last round
    k that scaled: the same piles a run that simulated every round kept). -> as
    `_size_rounds`."""
    sim, rounds = out / "sim", []
    for k in range(1, size_rounds + 1):
        chosen = tick(f"scale{k}", scale_check, file, data, out / f"size_round{k}", cfg)
        rounds.append(chosen)
        if chosen["scale"] == 1.0:
            break
        file, sim = Path(chosen["start"]), out / f"size_round{k}" / "sim"
    if cfg.family is not None and part is None and _renderer(file) == "spheres":
        choice = tick("family", family_stage, file, data, meta, view, out / "family", cfg,
                      progress, tick.budget)
        if choice["kept"] != "rod" or choice["scale"] != 1.0:
            sim = out / "family" / "sim"
            if choice["kept"] in FITTED:  # a fitted convex template: the model
                file = Path(choice["model"])
            # the piles are of the kept candidate at its scale; the model stays the rod for
            # the unfitted ones (a T, an L, discs, a ring, a taper: as with match_piles), and
            # keeps its own size
            part = Path(choice["part"])
    finished = _simulate_and_fit(file, data, meta, view, sim, out / "encoder", cfg,
                                 tick.seconds, "", progress, part)
    stages.update(1)
    return finished, sim, out / "encoder", rounds


def _renderer(file: Path) -> str:
    from inseggan_ros.core import checkpoint

    return checkpoint.load(file)["model_config"].get("renderer", "spheres")


def family_stage(file: Path, data, meta, view: dict, out: Path, cfg: LoopConfig,
                 progress: bool = True, budget: Budget | None = None) -> dict:
    """Stage 2c: the template family, chosen among `cfg.family`'s candidates made from the rod
    of `file` by how their piles and renders match the user's training frames (no label
    read; `family.choose`), within the budget's share -> the choice (out/family.json).
    Resumes candidate by candidate."""
    from inseggan_ros.core import checkpoint
    from inseggan_ros.learning import family
    from inseggan_ros.runtime.preprocess import PreprocessConfig

    prep = PreprocessConfig.from_dict(checkpoint.load(file)["preprocess_config"])
    frames = _user_frames(data, prep, "train", cfg.family.frames, progress)["x"]
    seconds = math.inf if budget is None else budget.share("family")
    choice = family.choose(file, frames, data, meta, view, out, cfg.family, progress, seconds)
    for row in choice["rows"] if budget is not None else ():
        if row.get("skipped", "").startswith(family.TIME_SKIP):
            budget.cut(f"family: {row['family']} {row['skipped']}")
    return choice


def _finishing_stages(finished: Path, sim: Path, view: dict, data, out: Path, cfg: LoopConfig,
                      tick, progress: bool) -> Path:
    """Stages 3 (head), 4 (self) and 4b (centres), those asked for -> the model to ship."""
    if cfg.head_iterations:
        finished = tick("head", label_head_stage, finished, sim, data, out / "head", cfg,
                        progress)
    if cfg.self_frames:
        finished = tick("self", self_stage, finished, data, out / "self", cfg, progress)
    if cfg.centre_iterations:
        folder = CENTRE_TEACHERS[cfg.centre_teacher]
        finished = tick("centres", centres_stage, finished, sim, view, data, out / folder, cfg,
                        progress, tick.budget)
    return finished


# of each candidate, on the card (width: a bars candidate's, times what `shapefit.rod_bars` makes)
CARD_FAMILY_KEYS = ("family", "scale", "pile_w1", "pile_w1_by_scale", "edge_w1", "recon_l1",
                    "score", "seconds", "refined", "width", "skipped")


def _export_stage(finished: Path, sim: Path, view: dict, data, cfg: LoopConfig, out: Path,
                  camera, recipe: dict | None, budget: Budget | None = None) -> dict:
    """Stage 5: the vote's scale chosen on the last piles' validation split (where
    `cfg.vote_scales` names scales; with centre votes taught on pasted piles, on the first 100
    of those that chose their iteration), then `_export` -> the card."""
    piles = None
    if cfg.vote_scales and cfg.centre_iterations and cfg.centre_teacher == "pasted":
        piles = _pasted_val(finished, data, cfg, 100)
    elif cfg.vote_scales:
        from inseggan_ros.data import datasets as data_mod

        piles = data_mod.load_sim_split(sim, "val", limit=100, **view)
    card = _export(finished, data, cfg, out / "model", piles, camera, recipe)
    if cfg.family is not None and (out / "family" / "family.json").is_file():
        _copy_atomic(out / "family" / "views.png", out / "model" / "template_family.png")
        chosen = json.loads((out / "family" / "family.json").read_text())
        card["template_family"] = {  # each candidate's scores and time, the one kept
            "kept": chosen["kept"], "scale": chosen["scale"], "seconds": chosen["seconds"],
            "edges": bool(chosen["config"].get("edges")),  # whether the edges' W1 was scored
            "candidates": [{k: r[k] for k in CARD_FAMILY_KEYS if k in r}
                           for r in chosen["rows"]]}
    card["verdict"] = verdict(card)  # the label-free judgement `inseggan ship` reads
    card["budget"] = budget.record() if budget is not None else None
    write_json(out / "model" / "card.json", card)
    readme = out / "model" / "README.md.tmp"  # again, with the verdict and the family; atomic
    readme.write_text(markdown(card))
    readme.replace(out / "model" / "README.md")
    return card


def _pasted_val(model: Path, data, cfg: LoopConfig, count: int) -> dict:
    """The first `count` validation piles the centres stage pasted (the same frames, seed and
    draws: `paste_splits` draws each split from its own seed), marked as the net's own."""
    from inseggan_ros.learning.pasted import PasteConfig, paste_splits
    from inseggan_ros.runtime.segment import Segmenter

    seg = Segmenter.from_checkpoint(model, device="cpu")
    frames = _user_frames(data, seg.prep_cfg, "train", None)
    val = paste_splits(frames, seg.model_cfg.n_instances, seg.prep_cfg,
                       PasteConfig(seed=cfg.seed, train=1, val=min(count, cfg.val_scenes)))["val"]
    return {**val, "taught": True}


def _copy_atomic(src: Path, dest: Path) -> None:
    """`src` copied to `dest` whole or not at all (where `src` exists)."""
    import shutil

    if src.is_file():
        tmp = dest.with_name(f".{dest.name}.tmp")
        shutil.copyfile(src, tmp)
        tmp.replace(dest)


def _summarise_templates(summary: dict, out: Path, planned: str, thickness: str,
                         size_rounds: int, rounds: list, part: Path | None) -> None:
    """The summary's account of the sizing and template stages: what was planned and run, the
    size stage's record, each round's scale, the matched discs."""
    summary["sizing"] = {"by_thickness": thickness, "rounds": size_rounds}
    if planned != thickness:
        summary["sizing"]["not_by_thickness"] = ("the folder's piles were made without the "
                                                 "size stage")
    if thickness != "off":
        summary["size"] = json.loads((out / "size" / "size.json").read_text())
    if size_rounds:
        summary["size_rounds"] = rounds
    if part is not None:
        match = json.loads((out / "match" / "search" / "summary.json").read_text())
        summary["match"] = {"part": str(part), "best": match["best"], "discs": match["discs"],
                            "variants": len(match["coarse"]) + len(match["fine"])}
