"""Ship a trained model: `models/<name>/` = model.pt (generator + encoder) + model card + PNG.

    inseggan export --checkpoint runs/cylinder/best.pt --data data/cylinder --name cylinder

1. tau is calibrated again on the data set's validation split with the inference settings the
   model ships with (test-time refinement steps), and stored in the checkpoint;
2. with --half the weights are stored in float16 only if that changes the validation mIoU by
   less than 0.002 (measured, and written in the card either way);
3. every method (InSeGAN and the classical baselines) is evaluated on the test split: mIoU on all
   frames and on the hard subset, time per frame; a qualitative PNG;
4. card.json (machine-readable: the test checks it against the checkpoint) and README.md.
Everything is written to a temporary folder first and moved into place at the end.

Without labels (a recording of the user's own part) `export_from_bag` does the same from the
frames alone (`selfcheck`): tau calibrated on the bag's first frames without labels, the card's
label-free measures (reconstruction error, coverage, instance count, time) on its last 20 %,
and mIoU against K-Means and Felzenszwalb only where a label topic is named:

    inseggan export --checkpoint runs/mine/best.pt --bag my_recording --name my_part
"""
from __future__ import annotations

import json
import math
import os
import platform
import shutil
import tempfile
from pathlib import Path

import numpy as np
from inseggan_ros.runtime.model import build_models


HALF_TOLERANCE = 0.002


def _val_miou(seg, val: dict) -> float:
    from inseggan_ros.evaluation import evaluate
    from inseggan_ros.core.metrics import mean_miou

    results = evaluate.run_methods(val, seg.model_cfg.n_instances, seg, methods=[], progress=False)
    return float(mean_miou(results["inseggan"]["scores"]))


def export_model(checkpoint_path, data_root, name: str, out_dir, inference=None,
                 half: bool = True, frames: int = 200, notes: str = "",
                 sample_bag: str | None = None, also: dict | None = None) -> dict:
    """Ship a trained model: out_dir/model.pt (inference weights, tau calibrated with the
    shipped `inference` settings, an InferenceConfig), card.json, README.md, qualitative.png.
    `also`: {name: InferenceConfig} of other settings measured on the test split as well (a
    row `inseggan_<name>` each)."""
    import torch

    from inseggan_ros.core import checkpoint as ckpt
    from inseggan_ros.data import datasets as data_mod
    from inseggan_ros.evaluation import evaluate
    from inseggan_ros.runtime.segment import InferenceConfig, Segmenter

    torch.set_num_threads(1)  # as the card says, and as the node runs by default: the pick
    # among refinement starts can tip with another thread count's rounding
    state = ckpt.load(checkpoint_path)
    seg = Segmenter.from_checkpoint(checkpoint_path, device="cpu")
    seg.inference = inference = inference or InferenceConfig()
    val = data_mod.load_sim_split(data_root, "val", seg.prep_cfg, limit=frames)
    test = data_mod.load_sim_split(data_root, "test", seg.prep_cfg, limit=frames)

    # 1. tau with the shipped inference settings
    seg.tau, scores = _calibrated_tau(seg, state, val)
    # as shipped: the calibration's own score where the labels are the z-buffer's alone
    plain = not seg.inference.smooth.iters and seg.inference.label_head == "off"
    val_full = scores[seg.tau] if plain and seg.tau in scores else _val_miou(seg, val)

    # 2. half precision only if it costs nothing measurable
    keep = _shipped_state(state, seg)
    precision, val_half = _half_precision(seg, state, keep, val, val_full) if half \
        else ("float32", None)
    keep["precision"] = precision

    # 3. the quality table on the test split (and, for reference, InSeGAN with more test-time
    # refinement than it ships with: better labels, slower frames)
    results = _test_results(seg, test, also)
    meta = json.loads((Path(data_root) / "meta.json").read_text())
    card = {
        "name": name, "object": meta["scene"]["object"], "n_instances": seg.model_cfg.n_instances,
        "camera": meta["scene"]["camera"], "noise": meta["scene"]["noise"],
        "data": {"root": str(data_root), "seed": meta.get("seed"), "counts": meta.get("counts")},
        "model_config": state["model_config"], "train_config_name": notes or None,
        "train_config": state["train_config"], "iterations": state["iteration"],
        "wall_minutes": round(state["elapsed_seconds"] / 60, 1),
        "hardware": f"{platform.machine()} CPU, {os.cpu_count()} cores (torch threads: 1)",
        "tau": seg.tau, **_settings_fields(seg, inference, also),
        "distillation": distill_record(state),
        "shape_fit": shape_fit_record(state), "centre_votes": centres_record(state),
        "precision": precision,
        "sample_bag": sample_bag,
        "sample_bag_scores": sample_bag_scores(seg, sample_bag) if sample_bag else None,
        "val_miou": {"float32": val_full, "float16": val_half},
        "test": evaluate.summarise(results, len(test["x"])),
    }
    _keep_training_runs(card, out_dir)
    _write_model_folder(out_dir, keep, card, test, results)
    return card


def _calibrated_tau(seg, state: dict, val: dict) -> tuple[float, dict]:
    """The tau of the segmenter's settings, on the z-buffered labels before smoothing, from the
    labelled validation frames -> (tau, {tau: score}); a label head's own tau where the model
    has one (it was trained on the z-buffer labels of that tau)."""
    import torch

    from inseggan_ros.runtime.segment import calibrate_tau, infer

    if state.get("label_head"):
        return float(state["label_head"]["tau"]), {}
    inference = seg.inference
    x = torch.from_numpy(val["x"])
    renders = torch.cat([infer(seg.G, seg.encoder(inference.encoder_precision), x[i:i + 50],
                               refine_steps=inference.refine_steps,
                               hypotheses=inference.refine_hypotheses,
                               keep=inference.refine_keep,
                               swaps=inference.refine_swaps)["renders"]
                         for i in range(0, len(x), 50)])
    return calibrate_tau(renders, torch.from_numpy(val["fg"]), val["labels"])


def _shipped_state(state: dict, seg) -> dict:
    """The checkpoint as a model folder keeps it: no training-only keys, the card's account of
    the distillation and of a shape fit (without the optimiser's state), tau and settings."""
    keep = {k: v for k, v in state.items() if k not in TRAINING_ONLY}
    keep["distill_record"] = distill_record(state)  # the card's account, kept for a re-fit
    fit = shape_fit_record(state)
    if fit:
        keep["shape_fit"] = fit
    keep["tau"] = seg.tau
    keep["inference"] = seg.inference.to_dict()
    return keep


def _half_precision(seg, state: dict, keep: dict, val: dict, val_full: float
                    ) -> tuple[str, float]:
    """The weights in float16 where that changes the validation mIoU by less than
    HALF_TOLERANCE (`keep`'s weights halved then; the segmenter left as it was otherwise) ->
    (the precision stored, the validation mIoU with float16 weights)."""
    G16, E16 = ({k: v.half().float() if v.is_floating_point() else v
                 for k, v in keep[key].items()} for key in ("generator", "encoder"))
    seg.G.load_state_dict(G16)
    seg.E.load_state_dict(E16)
    seg.encoder_changed()
    val_half = _val_miou(seg, val)
    if abs(val_half - val_full) < HALF_TOLERANCE:
        for key in ("generator", "encoder"):
            keep[key] = {k: v.half() if v.is_floating_point() else v
                         for k, v in keep[key].items()}
        return "float16", val_half
    seg.G.load_state_dict({k: v.float() for k, v in state["generator"].items()})
    seg.E.load_state_dict({k: v.float() for k, v in state["encoder"].items()})
    seg.encoder_changed()
    return "float32", val_half


def _keep_training_runs(card: dict, out_dir) -> None:
    """A re-export keeps the other runs the folder's card records on the same split."""
    previous = Path(out_dir) / "card.json"
    if previous.is_file():
        old_card = json.loads(previous.read_text())
        runs, old_data = old_card.get("training_runs"), old_card.get("data", {})
        if runs and old_data.get("root") == card["data"]["root"] \
                and old_data.get("counts") == card["data"]["counts"]:
            card["training_runs"] = runs


def apply_settings(model_dir, data_root, inference, also: dict | None = None) -> dict:
    """Ship a model with other test-time settings: models/<name>/model.pt stores `inference`
    (an InferenceConfig; weights and tau unchanged), and the card's settings, test table
    (every method again on the card's test split of `data_root`), validation mIoU, sample-bag
    scores and `also` rows are measured anew with it. The rest of the card (shape, training
    runs, distillation) is kept. tau stays: it is calibrated on the z-buffer's labels, before
    any step that `inference` can add after them."""
    import torch

    from inseggan_ros.core import checkpoint as ckpt
    from inseggan_ros.data import datasets as data_mod
    from inseggan_ros.evaluation import evaluate
    from inseggan_ros.runtime.segment import Segmenter

    torch.set_num_threads(1)  # as export measures
    model_dir = Path(model_dir)
    card = json.loads((model_dir / "card.json").read_text())
    meta = json.loads((Path(data_root) / "meta.json").read_text())
    if meta.get("seed") != card["data"]["seed"] or meta["scene"]["object"] != card["object"]:
        raise ValueError(f"{data_root}: seed {meta.get('seed')}, {meta['scene']['object']}; "
                         f"valid: the card's data set (seed {card['data']['seed']}, "
                         f"{card['object']}), whose test split the card reports")
    state = ckpt.load(model_dir / "model.pt")
    seg = Segmenter.from_checkpoint(model_dir / "model.pt", device="cpu")
    for cfg in (inference, *(also or {}).values()):
        seg.check(cfg)
    seg.inference = inference
    val = data_mod.load_sim_split(data_root, "val", seg.prep_cfg)
    test = data_mod.load_sim_split(data_root, "test", seg.prep_cfg)
    results = _test_results(seg, test, also)
    card.update({
        **_settings_fields(seg, inference, also), "centre_votes": centres_record(state),
        "val_miou": {"float32": None, "float16": None, card["precision"]: _val_miou(seg, val)},
        "test": evaluate.summarise(results, len(test["x"]))})
    if card.get("sample_bag"):
        card["sample_bag_scores"] = sample_bag_scores(seg, card["sample_bag"])
    state["inference"] = inference.to_dict()

    _write_model_folder(model_dir, state, card, test, results, keep_other_files=True)
    return card


def _test_results(seg, test: dict, also: dict | None) -> dict:
    """Every method on the test frames, InSeGAN with the segmenter's settings first, then a row
    `inseggan_<name>` for each of `also`'s {name: InferenceConfig}."""
    from inseggan_ros.evaluation import evaluate

    n = seg.model_cfg.n_instances
    results = evaluate.run_methods(test, n, seg, progress=True)
    shipped, extras = seg.inference, {}
    for name, other in (also or {}).items():
        seg.inference = other
        extras[f"inseggan_{name}"] = evaluate.run_methods(test, n, seg, methods=[],
                                                          progress=False)["inseggan"]
    seg.inference = shipped
    return {"inseggan": results.pop("inseggan"), **extras, **results}


def _settings_fields(seg, inference, also: dict | None) -> dict:
    """The card's record of the settings a model ships with (and of the `also` rows')."""
    return {
        "refine_steps": inference.refine_steps, "hypotheses": inference.refine_hypotheses,
        "smooth_iters": inference.smooth.iters, "keep": inference.refine_keep,
        "full_res_smooth_iters": inference.smooth.full_res_active,
        "inference": inference.to_dict(),
        # what "auto" meant here: the model tests measure in it, whatever their CPU computes
        # natively
        "encoder_precision": seg.resolve_precision(inference.encoder_precision),
        "centre_precision": seg.resolve_precision(inference.centre_precision),
        "also": {k: v.to_dict() for k, v in (also or {}).items()}}


def _write_model_folder(out_dir, state: dict, card: dict, test: dict, results: dict,
                        keep_other_files: bool = False) -> None:
    """model.pt, qualitative.png, card.json and README.md into `out_dir`, all at once; with
    `keep_other_files` the folder's other files (the shape drawing) are carried over."""
    from inseggan_ros.core import checkpoint as ckpt
    from inseggan_ros.evaluation import evaluate

    def write(tmp: Path) -> None:
        if keep_other_files:
            for f in Path(out_dir).iterdir():
                if f.is_file():
                    shutil.copy2(f, tmp / f.name)
        ckpt.save(tmp / "model.pt", state)
        evaluate.qualitative_png(tmp / "qualitative.png", test, results, count=4)
        (tmp / "card.json").write_text(json.dumps(card, indent=2))
        (tmp / "README.md").write_text(card_markdown(card))

    write_folder(out_dir, write)


def write_folder(out_dir, write) -> Path:
    """`write(tmp)` fills a temporary folder beside `out_dir`, which then replaces `out_dir`:
    a failed or interrupted export leaves the previous folder (or none) in place."""
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    os.chmod(tmp, 0o755)  # mkdtemp makes it private; a model folder is for everyone to read
    try:
        write(tmp)
        if out_dir.exists():
            shutil.rmtree(out_dir)
        os.replace(tmp, out_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out_dir


# Keys of a checkpoint that inference does not need (a training checkpoint's extras).
TRAINING_ONLY = ("discriminator", "optimizers", "rng", "format", "distill")


def export_label_free(checkpoint_path, name: str, out_dir, calib: dict, held: dict,
                      source: dict, inference=None, vote_piles: dict | None = None,
                      vote_scales=None, sample_bag: str | None = None, camera=None,
                      recipe: dict | None = None) -> dict:
    """Ship a model from frames without ground truth (a recording of the user's own part):
    out_dir/model.pt (inference weights, float32, tau calibrated on `calib` without labels,
    the inference settings), card.json, README.md, qualitative.png.

    `calib` and `held` are frame dicts (x, fg, labels or None; `selfcheck.load_bag_frames`):
    tau from `calib` (`selfcheck.calibrate`), the label-free measures on `held`
    (`selfcheck.measure`), and where `held` has labels, mIoU of InSeGAN, K-Means and
    Felzenszwalb on those frames too. `source` describes where the frames came from (for the
    card). `inference`: the test-time settings to ship (default: the checkpoint's).
    `vote_piles`: labelled frames ({x, fg, labels}: the loop's simulated piles) on which the
    superpixel vote's scale is chosen once tau is known (`vote_scale.choose`, among
    `vote_scales`, default `vote_scale.SCALES`). `sample_bag`: a shipped bag of the part with
    labels (`bags/`), scored as the model tests score it again (`sample_bag_scores`).
    `camera`: the camera the template was learned through (`sim.camera.CameraConfig`), which
    sizes it in metres (`inseggan simulate --object`, `card-shape`): recorded with the training
    data where the checkpoint's own record lacks it (a loop started from a data set's model,
    whose data set a clone does not have). `recipe`: the resolved configuration of the run
    that made the model (`inseggan loop`'s, with its `commit`), stored on the card as `recipe`
    and `commit`. Accepts a training checkpoint or an exported model.pt."""
    import torch

    from inseggan_ros.core import checkpoint as ckpt
    from inseggan_ros.evaluation import evaluate
    from inseggan_ros.evaluation import selfcheck

    torch.set_num_threads(1)  # as the card says, and as the node runs by default
    state = ckpt.load(checkpoint_path)
    seg, tau_scores, vote = _label_free_segmenter(checkpoint_path, state, calib, inference,
                                                  vote_piles, vote_scales)
    out = selfcheck.segment_frames(seg, held["x"], held["fg"])
    measures = selfcheck.measure(seg, held["x"], held["fg"], out)
    labelled = None
    if held.get("labels") is not None:
        results = evaluate.run_methods(held, seg.model_cfg.n_instances, seg,
                                       ["kmeans", "felzenszwalb"], progress=False)
        labelled = evaluate.summarise(results, len(held["x"]))
    keep = _label_free_state(state, seg, camera)
    card = {
        "name": name, "label_free": True, "n_instances": seg.model_cfg.n_instances,
        "model_config": state["model_config"], "train_config": state.get("train_config"),
        "training_data": keep.get("data"), "iterations": state.get("iteration"),
        "wall_minutes": round(state.get("elapsed_seconds", 0) / 60, 1),
        "checkpoint": str(checkpoint_path), "distillation": distill_record(state),
        "hardware": f"{platform.machine()} CPU, {os.cpu_count()} cores (torch threads: 1)",
        "source": source,
        "calibration": {"frames": len(calib["x"]), "index": _span(calib.get("index")),
                        "criterion": "IoU of the rendered foreground (max render >= tau) with "
                                     "the input's (x > -1), mean over frames",
                        "scores": {f"{t:.3f}": v for t, v in tau_scores.items()}},
        "held_out": {"frames": len(held["x"]), "index": _span(held.get("index")),
                     "stamp_ns": _span(held.get("stamp_ns"))},
        **_label_free_settings(seg),
        "measures": measures, "labelled": labelled, "vote_scale": vote,
        "shape_fit": shape_fit_record(state), "centre_votes": centres_record(state),
        "sample_bag": sample_bag,
        "sample_bag_scores": sample_bag_scores(seg, sample_bag) if sample_bag else None,
        **_recipe_fields(recipe),
    }

    def write(tmp: Path) -> None:
        ckpt.save(tmp / "model.pt", keep)
        selfcheck.sheet_png(tmp / "qualitative.png", held["x"], out, labels_gt=held.get("labels"))
        (tmp / "card.json").write_text(json.dumps(card, indent=2))
        (tmp / "README.md").write_text(label_free_markdown(card))

    write_folder(out_dir, write)
    return card


def _label_free_segmenter(checkpoint_path, state: dict, calib: dict, inference,
                          vote_piles: dict | None, vote_scales):
    """The segmenter a label-free export ships: `inference` (default: the checkpoint's), tau
    calibrated on `calib` without labels (a label head's own where the model has one), the
    vote's scale chosen on `vote_piles` where given (over centre votes, whether it runs at all
    by `calib`'s labels against the piles': `vote_scale.over_centres`) -> (segmenter, {tau:
    score}, the vote's choice or None)."""
    from dataclasses import replace

    from inseggan_ros.evaluation import selfcheck
    from inseggan_ros.evaluation import vote_scale
    from inseggan_ros.runtime.segment import Segmenter

    seg = Segmenter.from_checkpoint(checkpoint_path, device="cpu")
    if inference is not None:
        seg.inference = inference
    seg.tau, tau_scores = selfcheck.calibrate(seg, calib["x"], calib["fg"])
    if state.get("label_head"):  # a label head was trained on the z-buffer labels of its tau
        seg.tau = float(state["label_head"]["tau"])
    vote = None
    if vote_piles is not None:  # the renders, hence tau, do not depend on the vote; over
        # centre votes, `calib` (the user's frames) tells whether it runs at all
        vote = vote_scale.choose(seg, vote_piles, vote_scale.SCALES if vote_scales is None
                                 else vote_scales, frames=calib)
        seg.inference = replace(seg.inference, **{vote["setting"]: vote["scale"]})
    return seg, tau_scores, vote


def _label_free_state(state: dict, seg, camera) -> dict:
    """The checkpoint as a label-free model folder keeps it: no training-only keys, tau and
    settings, float32, the card's account of the distillation and of a shape fit (without the
    optimiser's state, twice the model's own size), and `camera` with the training data where
    the checkpoint's own record lacks one."""
    from dataclasses import asdict

    keep = {k: v for k, v in state.items() if k not in TRAINING_ONLY}
    keep.update(tau=seg.tau, inference=seg.inference.to_dict(), precision="float32",
                distill_record=distill_record(state))
    fit = shape_fit_record(state)
    if fit:
        keep["shape_fit"] = fit
    if camera is not None and not (state.get("data") or {}).get("camera"):
        keep["data"] = {**(state.get("data") or {}), "camera": asdict(camera)}
    return keep


def _label_free_settings(seg) -> dict:
    """A label-free card's record of tau and the settings the model ships with."""
    inf = seg.inference
    return {
        "tau": seg.tau, "refine_steps": inf.refine_steps, "hypotheses": inf.refine_hypotheses,
        "smooth_iters": inf.smooth.iters, "keep": inf.refine_keep, "inference": inf.to_dict(),
        "encoder_precision": seg.resolve_precision(inf.encoder_precision),
        "centre_precision": seg.resolve_precision(inf.centre_precision),
        "precision": "float32",  # no labels to show that float16 weights change nothing
    }


def _recipe_fields(recipe: dict | None) -> dict:
    """The card's `recipe` (the run's resolved configuration, every option) and `commit` (the
    code's git commit, or "unknown"), where the model was made by a run that resolved one."""
    if recipe is None:
        return {}
    from inseggan_ros.core.recipe import META, plain

    return {"recipe": plain({k: v for k, v in recipe.items() if k not in META}),
            "commit": recipe.get("commit", "unknown")}


def export_from_bag(checkpoint_path, bag, name: str, out_dir, depth_topic: str | None = None,
                    labels_topic: str | None = None, held_out: float = 0.2,
                    frames: int | None = 200, inference=None,
                    vote_piles: dict | None = None, vote_scales=None,
                    sample_bag: str | None = None, camera=None,
                    recipe: dict | None = None) -> dict:
    """`export_label_free` on a bag: tau from its first frames, the measures on its last
    `held_out` fraction (at most `frames` of each, spread evenly); labels only from
    `labels_topic`, when named."""
    from inseggan_ros.evaluation import selfcheck
    from inseggan_ros.core.checkpoint import CheckpointError, load
    from inseggan_ros.core.paths import resolve_bag
    from inseggan_ros.runtime.preprocess import PreprocessConfig

    path = resolve_bag(str(bag), "--bag")
    try:
        prep = PreprocessConfig.from_dict(load(checkpoint_path)["preprocess_config"])
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{checkpoint_path}: bad preprocessing config ({e})") from None
    all_frames = selfcheck.load_bag_frames(path, prep, depth_topic, labels_topic)
    calib, held = selfcheck.split_held_out(all_frames, held_out, frames)
    total = len(all_frames["x"])
    source = {"kind": "bag", "path": str(path), "depth_topic": depth_topic,
              "labels": labels_topic, "frames": total,
              "description": f"bag `{path}`",
              "held_out_rule": f"the last {100 * held_out:.0f} % of the bag's frames in time "
                               "order"}
    return export_label_free(checkpoint_path, name, out_dir, calib, held, source, inference,
                             vote_piles, vote_scales, sample_bag, camera, recipe)


def export_from_dataset(checkpoint_path, data_root, name: str, out_dir,
                        frames: int | None = 200, inference=None,
                        vote_piles: dict | None = None, vote_scales=None,
                        sample_bag: str | None = None, camera=None,
                        recipe: dict | None = None) -> dict:
    """`export_label_free` on a simulated data set, as if it had no labels: tau from its
    validation split without labels, the measures on its test split (whose labels give the
    mIoU rows)."""
    from inseggan_ros.data import datasets as data_mod
    from inseggan_ros.core.checkpoint import CheckpointError, load
    from inseggan_ros.runtime.preprocess import PreprocessConfig

    try:
        prep = PreprocessConfig.from_dict(load(checkpoint_path)["preprocess_config"])
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{checkpoint_path}: bad preprocessing config ({e})") from None
    calib = data_mod.load_sim_split(data_root, "val", prep, limit=frames)
    held = data_mod.load_sim_split(data_root, "test", prep, limit=frames)
    calib["labels"] = None  # label-free: tau from the frames alone
    if len(calib["x"]) == 0 or len(held["x"]) == 0:
        raise ValueError(f"{data_root}: needs frames in its val and test splits")
    source = {"kind": "data set", "path": str(data_root), "labels": "the data set's test split",
              "frames": len(calib["x"]) + len(held["x"]),
              "description": f"simulated data set `{data_root}` (val and test splits)",
              "held_out_rule": "its test split"}
    return export_label_free(checkpoint_path, name, out_dir, calib, held, source, inference,
                             vote_piles, vote_scales, sample_bag, camera, recipe)


def _span(values) -> list[int] | None:
    """[first, last] of a frame index or stamp array, for the card."""
    if values is None or len(values) == 0:
        return None
    return [int(values[0]), int(values[-1])]


def _frames_text(part: dict) -> str:
    """' (frames a to b of the bag)' where the card knows them."""
    return f" (frames {part['index'][0]} to {part['index'][1]})" if part.get("index") else ""


def label_free_markdown(card: dict) -> str:
    """README.md of a model exported from frames without labels (`export_label_free`)."""
    from inseggan_ros.evaluation.evaluate import format_table
    from inseggan_ros.evaluation.selfcheck import format_measures

    src, m, held, cal = card["source"], card["model_config"], card["held_out"], card["calibration"]
    data = card.get("training_data") or {}
    trained = (f"{data.get('source', '?')} `{data.get('path', '?')}` "
               f"({data.get('train_frames', '?')} training frames)" if data else "unknown")
    lines = [
        f"# Model card: {card['name']}", "",
        f"* **Model:** n = {card['n_instances']} per bin, renderer {_template_text(m)}, composite "
        f"{m['composite']}, nf {m['nf']}, latent {m['latent_dim']}",
        f"* **Training:** {trained}; {card['iterations']} iterations, {card['wall_minutes']} min "
        f"wall time",
        *_distill_line(card), *_recipe_line(card), *_family_line(card), *_budget_line(card),
        f"* **Checked on:** {src['description']}: {src['frames']} frames. tau calibrated without "
        f"labels on {cal['frames']} frames{_frames_text(cal)}, measured on {held['frames']} "
        f"held-out frames{_frames_text(held)}: {src['held_out_rule']}",
        f"* **Inference:** tau {card['tau']:.3f} (from the frames: {cal['criterion']}), "
        + _settings_text(card["inference"]) + f", weights stored in {card['precision']}; "
        f"{card['hardware']}",
        *_vote_line(card), *_centres_line(card), "",
        "## Label-free measures on the held-out frames", "",
        *[f"* {line}" for line in format_measures(card["measures"]).splitlines()], "",
        "Reconstruction L1: the z-buffered render against the model's 64 x 64 input; coverage: "
        "the input-foreground pixels where some instance's render reaches tau; a visible "
        f"instance labels at least {card['measures']['min_visible_pixels']} of the 64 x 64 "
        "pixels.", "",
        *_verdict_lines(card),
    ]
    if card.get("labelled"):
        lines += [f"## Against the ground truth ({src.get('labels')})", "",
                  format_table(card["labelled"]), ""]
    lines += [*_bag_line(card),
              "![qualitative](qualitative.png): input | reconstruction | labels | each instance "
              "rendered alone" + (" | ground truth" if card.get("labelled") else ""), "",
              *_shape_lines(card)]
    return "\n".join(lines)


def _family_line(card: dict) -> list[str]:
    """The README's line on the template family the loop chose, where it chose one."""
    fam = card.get("template_family")
    if not fam:
        return []
    rows = ", ".join(f"{r['family']} {r['score']:.2f} (W1 {r['pile_w1']:.3f} at x{r['scale']:g}, "
                     + (f"bars x{r['width']:g} wide, " if "width" in r else "")
                     + (f"edges' W1 {r['edge_w1']:.3f}, " if "edge_w1" in r else "")
                     + f"reconstruction {r['recon_l1']:.3f}, {r['seconds'] / 60:.1f} min)"
                     if "score" in r else f"{r['family']} not made ({r['skipped']})"
                     for r in fam["candidates"])
    return [f"* **Template family:** {fam['kept']} kept, its piles at x{fam['scale']:g}, of: "
            f"{rows}; the score is the piles' heights' W1 to the frames over the best, plus "
            + ("their edge distances' W1 over the best, plus " if fam.get("edges") else "")
            + "the held-out reconstruction over the best (`family/family.png` in the loop's "
            "folder); "
            "each candidate from the top, the front and the side: "
            "![candidates](template_family.png)"]


def _budget_line(card: dict) -> list[str]:
    """The README's line on the loop's time budget, where it had one."""
    b = card.get("budget")
    if not b or not b["minutes"]:
        return []
    return [f"* **Time budget:** {b['minutes']:g} min, {b['used_minutes']:g} used to the export"
            + (" (over it)" if b["over"] else "") + "; "
            + ("cut: " + "; ".join(b["cut"]) if b["cut"] else "nothing cut")]


def _verdict_lines(card: dict) -> list[str]:
    """The README's section on the loop's label-free verdict, where the card has one."""
    v = card.get("verdict")
    if v is None:
        return []
    if v["ok"]:
        return ["**Verdict:** the label-free measures show a model that explains its frames "
                "(`evaluation/verdict.py`).", ""]
    return ["**Verdict: the model does not explain its frames.**", "",
            *[f"* {line}" for line in v["problems"]], ""]


def _recipe_line(card: dict) -> list[str]:
    """The README's line on the recipe the card stores, where it stores one."""
    if "recipe" not in card:
        return []
    return [f"* **Recipe:** `inseggan loop` with the card's `recipe` (every option; "
            f"`inseggan ship` writes it as config/recipes/{card['name']}.yaml), code commit "
            f"{card.get('commit', 'unknown')}"]


def sample_bag_scores(seg, bag_name: str) -> dict:
    """Scores of InSeGAN (as shipped) and K-Means on a shipped sample bag's frames, at 64 x 64, and
    at the bag's full resolution as the segmenter node runs by default: what the model and node
    tests check again."""
    from inseggan_ros.data import datasets as data_mod
    from inseggan_ros.evaluation import evaluate
    from inseggan_ros.core.metrics import mean_miou
    from inseggan_ros.core.paths import resolve_bag

    path = resolve_bag(bag_name)
    frames = data_mod.load_bag(path, seg.prep_cfg)
    results = evaluate.run_methods(frames, seg.model_cfg.n_instances, seg, ["kmeans"],
                                   progress=False)
    return {"frames": len(frames["x"]),
            "inseggan": float(mean_miou(results["inseggan"]["scores"])),
            "kmeans": float(mean_miou(results["kmeans"]["scores"])),
            "full_resolution": full_resolution_scores(seg, path)}


def full_resolution_scores(seg, bag_path) -> dict:
    """Scores of InSeGAN and K-Means at the bag's own resolution, against its ground truth.

    InSeGAN as the segmenter node runs with its defaults (bin region found in the first frames,
    floor depth estimated per frame), labels mapped back to every input pixel and carried onto
    objects just outside the region (`preprocess.extend_labels`); K-Means on (x, y, depth) of
    the ground-truth foreground of the same frames (the true foreground, pixels outside the bin
    region included: a mask InSeGAN does not get)."""
    from inseggan_ros.io import bags
    from inseggan_ros.evaluation.baselines import kmeans
    from inseggan_ros.core.metrics import mean_miou, miou_batch
    from inseggan_ros.runtime.preprocess import BIN_FRAMES, node_defaults

    frames = bags.read_all(bag_path)
    prep = node_defaults(seg.prep_cfg, [f.metres() for f in frames[:BIN_FRAMES]])
    n = seg.model_cfg.n_instances
    ours, km, gt = [], [], []
    for f in frames:
        depth = f.metres()
        ours.append(seg(depth, prep, reconstruction=False).labels)
        km.append(kmeans(-depth, f.labels > 0, n))
        gt.append(f.labels)
    gt = np.stack(gt)
    return {"inseggan": float(mean_miou(miou_batch(np.stack(ours), gt))),
            "kmeans": float(mean_miou(miou_batch(np.stack(km), gt)))}


def _settings_text(d: dict) -> str:
    from inseggan_ros.runtime.segment import InferenceConfig

    cfg = InferenceConfig.from_dict(d)
    smooth = cfg.smooth
    swaps = (f", up to {cfg.refine_swaps} instances of the other starting points swapped in"
             if cfg.refine_swaps and cfg.refine_hypotheses > 1 else "")
    if cfg.refine_steps == 0:
        start = (f"no refinement, the best-fitting of {cfg.refine_hypotheses} starting points"
                 f"{swaps}" if cfg.refine_hypotheses > 1 else "no refinement")
    elif cfg.refine_keep == 1 and cfg.refine_hypotheses > 1:
        start = (f"the best-fitting of {cfg.refine_hypotheses} starting points{swaps}, then "
                 f"{cfg.refine_steps} refinement iterations")
    else:
        keep = f", the best-fitting {cfg.refine_keep} refined" if cfg.refine_keep else ""
        after = (f", then up to {cfg.refine_swaps} instances of the other refined starting points "
                 "swapped in" if cfg.refine_swaps and cfg.refine_hypotheses > 1 else "")
        start = (f"{cfg.refine_steps} refinement iterations from {cfg.refine_hypotheses} starting "
                 f"point(s){keep}{after}")
    precision = ("" if cfg.encoder_precision == "float32"
                 else f", encoder in {cfg.encoder_precision}")
    head = ", labels from the label head" if cfg.label_head == "on" else ""
    if cfg.centre_votes == "on":
        net = "" if cfg.centre_precision == "float32" else f" (net in {cfg.centre_precision})"
        head = f", instances from the centre votes{net}"
    vote = (f", then voted within depth superpixels (scale {cfg.vote_scale})"
            if cfg.vote_scale else "")
    split = (f", missed parts split off along coarse depth segments (scale {cfg.split_scale})"
             if cfg.split_scale else "")
    return (f"{start}{head}, {smooth.iters} smoothing iterations + {smooth.full_res_active} at "
            f"full resolution{vote}{split}{precision}")


def centres_record(state: dict) -> dict | None:
    """The card's account of a model's centre votes (`centres.fit`), without the weights."""
    net = state.get("centre_net")
    if not net:
        return None
    summary = net.get("summary", {})
    return {"width": net["width"], "sim": net.get("sim"), "piles_part": net.get("piles_part"),
            "teacher": net.get("teacher", "piles"),
            "teacher_settings": net.get("teacher_settings"),
            "iterations": summary.get("config", {}).get("iterations"),
            "train_frames": summary.get("train_frames"),
            "val_frames": summary.get("val_frames"),
            "best_val_miou": summary.get("best_val_miou"), "seconds": summary.get("seconds")}


def _centres_line(card: dict) -> list[str]:
    """Where the model's centre votes were taught, and whether its settings use them."""
    c = card.get("centre_votes")
    if not c:
        return []
    used = "on" if card["inference"].get("centre_votes") == "on" else "off in these settings"
    best = "?" if c.get("best_val_miou") is None else f"{c['best_val_miou']:.3f}"
    if str(c.get("teacher")).startswith("self-labels"):
        votes = "on" if c["teacher"].endswith("centre votes") else "off"
        with_ = (f" with the settings of `{c['teacher_settings']}`"
                 if c.get("teacher_settings") not in (None, "own") else "")
        return [f"* **Centre votes** ({used}): a {c['width']}-wide network taught on "
                f"{c.get('train_frames')} of the data set's own training frames (`{c.get('sim')}`"
                f"), labelled by this model itself{with_} with its centre votes {votes} (no "
                f"true label read), {c.get('iterations')} iterations; agreement with those "
                f"labels on {c.get('val_frames')} more frames {best}"]
    if c.get("teacher") == "pasted piles":
        return [f"* **Centre votes** ({used}): a {c['width']}-wide network taught on "
                f"{c.get('train_frames')} piles pasted from the {c.get('piles_part')} "
                f"(`{c.get('sim')}`; no template, no label), {c.get('iterations')} iterations; "
                f"mIoU on {c.get('val_frames')} more such piles {best}"]
    return [f"* **Centre votes** ({used}): a {c['width']}-wide network taught on "
            f"{c.get('train_frames')} labelled simulated piles of "
            f"{c.get('piles_part') or 'the learned part'} (`{c.get('sim')}`), "
            f"{c.get('iterations')} iterations; mIoU on {c.get('val_frames')} more piles {best}"]


def _vote_line(card: dict) -> list[str]:
    """The vote's scale where it was chosen on labelled piles (`vote_scale`)."""
    from inseggan_ros.evaluation.vote_scale import describe

    vote = card.get("vote_scale")
    return [f"* **Vote:** {describe(vote)}"] if vote else []


def _distill_line(card: dict) -> list[str]:
    """The encoder's training after the shape stage, one line per step, oldest first."""
    steps, d = [], card.get("distillation")
    while d:
        steps.insert(0, d)
        d = d.get("previous")
    return [_self_fit_text(d) if d.get("self_fit") else _distill_text(d) for d in steps]


def _self_fit_text(d: dict) -> str:
    s, c = d["self_fit"], d["config"]
    return ("* **Encoder fitted further to its own labels** (`inseggan self-fit` or the loop's "
            f"`--self-frames`): the model's labels at `{s['settings']}` settings (tau "
            f"{s['tau']:.2f}) of {c['frames']} of the user's unlabelled training frames (no "
            "label of the data is read), the label and "
            f"ownership losses, the last of {d['iterations']} iterations "
            f"({d['wall_minutes']} min, learning rate cosine to 0)")


def _distill_text(d: dict) -> str:
    c, v = d["config"], d["val_miou_no_refinement"]
    before = f"{v['before']:.3f} -> " if v["before"] is not None else ""
    narrow = (f" into a {c['encoder_nf']}-wide encoder pruned from the source's "
              f"(`--encoder-nf {c['encoder_nf']}`)" if c.get("encoder_nf") else "")
    schedule = ", learning rate cosine to 0" if c.get("lr_schedule") == "cosine" else ""
    pose, label = c.get("lambda_pose", 1.0) > 0, c.get("lambda_label", 0.0) > 0
    targets = []
    if pose:
        targets.append(f"its refined poses of {c['frames']} training frames "
                       f"({c['refine_steps']} iterations x {c['hypotheses']} starts)")
    if label:
        targets.append(f"the known labels of {c['frames']} simulated piles of its own learned "
                       "part (`inseggan loop`: no label of the training data is used)")
    user = (", while reconstructing the user's own unlabelled frames (weight "
            f"{c['lambda_user']:g})" if c.get("lambda_user", 0.0) > 0 else "")
    where = " on those simulated piles" if label and not pose else ""
    val = (f"; validation mIoU without refinement{where} {before}{v['best']:.3f}"
           if v["best"] is not None else "")
    return (f"* **Encoder distilled** (`inseggan distill`){narrow} on " + " and ".join(targets)
            + f"{user}, best of {c['iterations']} iterations at {d['iterations']} "
            f"({d['wall_minutes']} min of fine-tuning{schedule}){val}")


def _bag_line(card: dict) -> list[str]:
    b = card.get("sample_bag_scores")
    if not b:
        return []
    full = b.get("full_resolution")
    return [f"On the {b['frames']} frames of the shipped sample bag `{card['sample_bag']}`: "
            f"InSeGAN {b['inseggan']:.3f}, K-Means {b['kmeans']:.3f} at 64 x 64"
            + (f"; at the bag's full resolution (the segmenter node's output) InSeGAN "
               f"{full['inseggan']:.3f}, K-Means {full['kmeans']:.3f}" if full else "") + ".", ""]


def _dims(f: dict) -> tuple[str, str]:
    """A shape record's learned and true dimensions, "L x W x H" in mm each."""
    return tuple(" x ".join(f"{v:.1f}" for v in f[k])
                 for k in ("dims_template_mm", "dims_true_mm"))


def _shape_lines(card: dict) -> list[str]:
    f = card.get("shape")
    if not f:
        return []
    dims, true = _dims(f)
    fit = card.get("shape_fit")
    how = ([f"The template is {fit['config']['pieces']} convex piece(s) fitted by "
            f"reconstruction of the unlabelled training frames (`inseggan shape-fit`, "
            f"{fit['iterations']} iterations from the rod model `{fit['source']}`; kept: "
            f"iteration {fit['kept']}, "
            + ("the best held-out reconstruction" if fit["kept"] == fit["best"] else
               f"the held-out reconstruction was best at iteration {fit['best']}") + ").",
            ""] if fit else [])
    return ["## Learned shape", "", *how,
            f"The learned template against the simulator's true {f['object']} "
            f"(`inseggan card-shape`): volumetric IoU {f['iou']:.3f} after the best alignment "
            f"({f['voxel_mm']:.1f} mm voxels){' (the mirror image)' if f['mirrored'] else ''}; "
            f"length x width x height {dims} mm learned vs {true} mm true (mean relative error "
            f"{100 * f['dims_rel_error']:.1f} %). Top row the template, bottom row the part, "
            "seen from the top, the front and the side:", "",
            "![learned shape vs true part](shape.png)", "", *_piles_shape_lines(card)]


def _piles_shape_lines(card: dict) -> list[str]:
    f = card.get("piles_shape")
    if not f:
        return []
    dims, true = _dims(f)
    return [f"The template the centre votes' piles are of (`{f['template']}`, made from the "
            f"template above: see Centre votes) against the same part: volumetric IoU "
            f"{f['iou']:.3f}, {dims} mm vs {true} mm (mean relative error "
            f"{100 * f['dims_rel_error']:.1f} %):", "",
            "![piles' template vs true part](piles_shape.png)", ""]


def add_shape(model_dir, object_name: str | None = None, voxels: int = 30,
              piles_template=None) -> dict:
    """Measure a shipped model's learned template against the simulator's true part (the card's
    object, or `object_name`): `shape.fit` at `voxels` voxels along the part's largest extent,
    the three-view drawing as shape.png, the numbers as card["shape"], README.md written again;
    the folder is replaced atomically. The template's scale comes from the card's camera and the
    model's crop, so no data set is needed. `piles_template`: the learned template (a model
    file) the centre votes' piles were of, where it is not the model's own (the bolt's discs):
    measured the same way as card["piles_shape"] and piles_shape.png. -> the shape record."""
    from inseggan_ros.core import checkpoint as ckpt
    from inseggan_ros.evaluation import shape
    from inseggan_ros.sim.learned import model_camera
    from inseggan_ros.sim.objects import OBJECTS

    model_dir = Path(model_dir)
    card = json.loads((model_dir / "card.json").read_text())
    name = object_name or card.get("object")  # a recording's card names no part
    if name is None:
        raise ValueError(f"{model_dir}: its card names no part (a model made from a recording); "
                         f"valid: --object, one of {', '.join(OBJECTS)}")
    if name not in OBJECTS:
        raise ValueError(f"{name!r}: not a part of the simulator's library, so there is no true "
                         f"shape to compare with; valid: {', '.join(OBJECTS)}")
    state = ckpt.load(model_dir / "model.pt")
    if state["model_config"].get("renderer") not in ("spheres", "convex"):
        raise ValueError(f"{model_dir}: renderer {state['model_config'].get('renderer')!r} has "
                         "no explicit template; valid: 'spheres' or 'convex'")
    voxel = shape.part_voxel(name, voxels)
    camera = model_camera(model_dir, state)
    if camera is None:
        raise ValueError(f"{model_dir}: its card records no camera, so the template's size in "
                         "metres is unknown; valid: a card made by `inseggan export` or "
                         "`inseggan loop` (a data set's camera, or a recording's estimated one)")

    def measure(file: Path, drawing: Path) -> dict:
        st = ckpt.load(file)
        scale = shape.metres_per_unit(st["preprocess_config"], camera,
                                      st["model_config"]["height_gain"])
        G = build_models(st, file)[1]
        f = shape.evaluate_generator(G, name, scale, drawing, voxel=voxel)
        del f["drawing"]  # the folder's drawing, not the temporary path
        return f

    def write(tmp: Path) -> None:
        drawn = ("card.json", "README.md", "shape.png") + (
            ("piles_shape.png",) if piles_template is not None else ())
        for f in model_dir.iterdir():
            if f.is_file() and f.name not in drawn:
                shutil.copy2(f, tmp / f.name)
        card["shape"] = measure(model_dir / "model.pt", tmp / "shape.png")
        if piles_template is not None:
            card["piles_shape"] = {**measure(Path(piles_template), tmp / "piles_shape.png"),
                                   "template": str(piles_template)}
        (tmp / "card.json").write_text(json.dumps(card, indent=2))
        (tmp / "README.md").write_text(markdown(card))

    write_folder(model_dir, write)
    return card["shape"]


def add_training_run(model_dir, checkpoint_path, eval_results, label: str,
                     hardware: str) -> dict:
    """Record on a model card another training run of the same part (another config, more
    compute, a GPU), scored by `inseggan eval` on the card's own test frames, so that the card
    shows what the shipped recipe is measured against. The run is described from its checkpoint
    (config, iterations, wall time) and `hardware`; the scores from `eval_results` (results.json),
    which must be of the card's data set and test split, all of its test frames. A run of the
    same label replaces the earlier one; the folder is replaced atomically. -> the record."""
    from inseggan_ros.core import checkpoint as ckpt

    model_dir = Path(model_dir)
    card = json.loads((model_dir / "card.json").read_text())
    res = json.loads(Path(eval_results).read_text())
    frames = card["test"]["frames"]
    scored = str(res.get("data", ""))
    if scored != f"{card['data']['root']} (test)":
        raise ValueError(f"{eval_results}: scored on {scored!r}; valid: the card's test split "
                         f"'{card['data']['root']} (test)'")
    if res.get("frames") != frames:
        raise ValueError(f"{eval_results}: {res.get('frames')} frames scored, the card's test "
                         f"split has {frames}: score the run on all of them")
    state = ckpt.load(checkpoint_path)
    t = state["train_config"]
    m = res["methods"]["inseggan"]
    centres = centres_record(state) or {}  # its centre-vote net, where it has one
    record = {"label": label, "checkpoint": str(checkpoint_path), "hardware": hardware,
              "nf": t["model"]["nf"],  # what renders: a shape fit makes a rod model convex
              "renderer": state["model_config"].get("renderer", t["model"]["renderer"]),
              "composite": t["model"]["composite"], "batch_size": t["batch_size"],
              "iterations": int(state["iteration"]),
              "wall_minutes": round(float(state["elapsed_seconds"]) / 60, 1),
              "encoder_iterations": int(state["distill"]["iteration"])
              if state.get("distill") else 0,  # the encoder fitted further (`inseggan distill`)
              "encoder_minutes": round(float(state["distill"]["seconds"]) / 60, 1)
              if state.get("distill") else 0.0,
              "centre_iterations": centres.get("iterations") or 0,
              "centre_minutes": round(float(centres.get("seconds") or 0) / 60, 1),
              "settings": {k: res[k] for k in ("refine_steps", "refine_hypotheses",
                                               "smooth_iters")},
              "miou_all": m["miou_all"], "miou_hard": m.get("miou_hard"),
              "miou_hard_felzenszwalb": m.get("miou_hard_felzenszwalb"),
              "ms_per_frame": m["ms_per_frame"]}

    def write(tmp: Path) -> None:
        for f in model_dir.iterdir():
            if f.is_file() and f.name not in ("card.json", "README.md"):
                shutil.copy2(f, tmp / f.name)
        runs = [r for r in card.get("training_runs", []) if r["label"] != label]
        card["training_runs"] = runs + [record]
        (tmp / "card.json").write_text(json.dumps(card, indent=2))
        (tmp / "README.md").write_text(card_markdown(card))

    write_folder(model_dir, write)
    return record


def _runs_lines(card: dict) -> list[str]:
    runs = card.get("training_runs")
    if not runs:
        return []

    def f(v):
        return "-" if v is None else f"{v:.3f}"

    lines = ["## Other training runs", "",
             "Other runs on the same test frames (`inseggan card-run`), with the settings of "
             "their row (refinement steps, starting points, smoothing iterations; 0, 1, 0: the "
             "GAN's own encoder alone); iterations and minutes up to the checkpoint kept (the "
             "best on the validation frames), the GAN's, then (+) the encoder's fitted further "
             "where it was, then (+) the centre-vote net's where it has one; milliseconds a "
             "frame on the CPU that scored it:", "",
             "| run | hardware | template, nf, batch | iterations | minutes | settings "
             "(refine, starts, smooth) | all | hard: K-Means | hard: Felzenszwalb | ms / frame |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        s = r["settings"]
        its, mins = str(r["iterations"]), str(r["wall_minutes"])
        if r.get("encoder_iterations"):
            its += f" + {r['encoder_iterations']}"
            mins += f" + {r['encoder_minutes']}"
        if r.get("centre_iterations"):
            its += f" + {r['centre_iterations']} (centre votes)"
            mins += f" + {r['centre_minutes']}"
        lines.append(
            f"| {r['label']} | {r['hardware']} | {r['renderer']} ({r['composite']}), "
            f"{r['nf']}, {r['batch_size']} | {its} | {mins} | "
            f"{s['refine_steps']}, {s['refine_hypotheses']}, {s['smooth_iters']} | "
            f"{f(r['miou_all'])} | {f(r['miou_hard'])} | {f(r['miou_hard_felzenszwalb'])} | "
            f"{r['ms_per_frame']:.1f} |")
    return lines + [""]


def distill_record(state: dict) -> dict | None:
    """What `inseggan distill` (or `self-fit`, `loop`) did to the encoder of this checkpoint, if
    anything, with what was done before it ("previous"); an exported model keeps it as
    "distill_record"."""
    d = state.get("distill")
    if not d:
        return state.get("distill_record")
    val = [h for h in d["history"] if h["kind"] == "val"]
    best = d["best"] if math.isfinite(d["best"]) else None  # none without validation frames
    return {"config": d["config"], "iterations": d["iteration"],
            "wall_minutes": round(d["seconds"] / 60, 1),
            "val_miou_no_refinement": {"before": val[0].get("miou") if val else None,
                                       "best": best},
            "previous": d.get("previous"), "self_fit": d.get("self_fit")}


def shape_fit_record(state: dict) -> dict | None:
    """How `inseggan shape-fit` made this checkpoint's convex template from a rod model, if it
    did: its config, the rod model, the iterations, the validation reconstruction error at
    each evaluation and the one kept (the lowest)."""
    d = state.get("shape_fit")
    if not d:
        return None
    if "optimizer" not in d:  # already the record
        return d
    val = [(h["iteration"], h["recon_l1"]) for h in d["history"]
           if h["kind"] == "val" and "recon_l1" in h]
    return {"config": d["config"], "source": d["source"],
            "iterations": d["config"]["iterations"], "wall_minutes": round(d["seconds"] / 60, 1),
            "val_recon_l1": val, "kept": d["iteration"],  # this checkpoint's own
            "best": min(val, key=lambda v: v[1])[0] if val else None}


def _template_text(m: dict) -> str:
    """The template as a reader needs it: the renderer and its size (a rod's sphere count
    bounds how long it can be for its thickness; a convex template's piece count)."""
    if m["renderer"] == "spheres" and "spheres" in m:
        return f"spheres ({m['spheres']} on the rod's axis)"
    if m["renderer"] == "convex" and "pieces" in m:
        return f"convex ({m['pieces']} pieces)"
    return m["renderer"]


def markdown(card: dict) -> str:
    """A model folder's README.md: its card as `export` (or `export --bag`) writes it."""
    return label_free_markdown(card) if card.get("label_free") else card_markdown(card)


def card_markdown(card: dict) -> str:
    from inseggan_ros.evaluation.evaluate import format_table

    cam = card["camera"]
    noisy = any(card["noise"].get(k, 0) for k in ("sigma_base", "sigma_per_m2", "edge_dropout",
                                                  "random_dropout", "quantum"))
    noise = "RealSense-like sensor noise" if noisy else "none"
    m = card["model_config"]
    lines = [
        f"# Model card: {card['name']}", "",
        f"* **Object:** {card['object']}, n = {card['n_instances']} per bin",
        f"* **Camera:** {cam['width']}x{cam['height']}, fx {cam['fx']}, mounted "
        f"{cam['mount_height']} m above the bin floor; noise: {noise}",
        f"* **Data:** simulated, seed {card['data']['seed']}, scenes {card['data']['counts']}",
        f"* **Model:** renderer {_template_text(m)}, composite {m['composite']}, nf {m['nf']}"
        + (f" (encoder {m['encoder_nf']})" if m.get("encoder_nf") else "") + ", "
        f"latent {m['latent_dim']}, coord_conv {m.get('coord_conv', False)}",
        f"* **Training:** {card['iterations']} iterations, {card['wall_minutes']} min wall time, "
        f"{card['hardware']}, batch {card['train_config']['batch_size']}",
        *_distill_line(card),
        f"* **Inference:** tau {card['tau']:.3f} (calibrated on the 200 validation scenes), "
        + _settings_text(card["inference"]) + f", weights stored in {card['precision']} "
        f"(validation mIoU float32 {card['val_miou']['float32']:.4f}"
        + (f", float16 {card['val_miou']['float16']:.4f}"
           if card['val_miou']['float16'] is not None else "")
        + ")", *_centres_line(card), "",
        "## Test split (held-out scenes)", "",
        format_table(card["test"]), "",
        "Hard subset: frames where K-Means scores below 0.6 (the paper's choice of test images).",
        "`inseggan` is the model as shipped (what the segmenter node runs by default, with the",
        "settings above); `inseggan_<name>`, where present, the same model with other test-time",
        "settings (`config/<name>.yaml`, the node's parameters):",
        *[f"* `inseggan_{k}`: {_settings_text(v)}" for k, v in card.get("also", {}).items()],
        "",
        *_bag_line(card),
        "![qualitative](qualitative.png)", "",
        *_shape_lines(card),
        *_runs_lines(card),
    ]
    return "\n".join(lines)
