"""Whether a model made from a recording explains its frames, judged without a label.

A loop can fail without knowing the truth: its renders cover little of the parts the frames
show (coverage), draw parts where the frames have none (spill), its centre votes score low on
their own held-out piles, or the rendered foreground matches the input's poorly at every
threshold, or its labels cross the frames' height edges far more often than its own piles'
(the template is not the part's shape: `vote_scale.over_centres`). The shipped recording-made
models measure coverage 0.68-0.92, spill 0.12-0.28, centre
votes 0.75-0.92 on their piles and a foreground IoU of 0.56-0.82 at their tau
(models/*/card.json); a model whose coverage is 0.05 explains nothing. Each rule here sits well
below the worst shipped model, so a warning means a model that does not explain its frames, not
a weak one. `inseggan loop` prints the verdict and stores it in the card; `inseggan ship`
refuses a failing model unless told otherwise.
"""
from __future__ import annotations

MIN_COVERAGE = 0.4  # of the input's part pixels explained by a render
MAX_SPILL = 0.6  # of the rendered part pixels where the input has none
MIN_CENTRE_MIOU = 0.5  # the centre votes' mIoU on their own validation piles
MIN_FOREGROUND_IOU = 0.35  # the rendered foreground against the input's, at the model's tau


def _best_foreground_iou(card: dict) -> float | None:
    scores = (card.get("calibration") or {}).get("scores") or {}
    return max(scores.values()) if scores else None


def problems(card: dict) -> list[str]:
    """What in a model card's label-free figures says the model does not explain its frames:
    one line per problem, with the figure, the bar and what to try. [] = none found."""
    m = card.get("measures") or {}
    out = []
    cov, spill = m.get("coverage"), m.get("spill")
    if cov is not None and cov < MIN_COVERAGE:
        out.append(f"coverage {cov:.3f} < {MIN_COVERAGE}: the renders explain little of the "
                   "parts in the frames; the parts may be too small in the model's view (record "
                   "the bin nearer, or with the camera's view filled by it) or the shape stage "
                   "learned no part (give the loop more --minutes)")
    if spill is not None and spill > MAX_SPILL:
        out.append(f"spill {spill:.3f} > {MAX_SPILL}: the renders draw parts where the frames "
                   "have none; check --instances against the parts in the bin")
    votes = (card.get("centre_votes") or {}).get("best_val_miou")
    if votes is not None and votes < MIN_CENTRE_MIOU:
        out.append(f"centre votes mIoU {votes:.3f} < {MIN_CENTRE_MIOU} on their own piles: the "
                   "simulated piles are hard to separate even with their labels; the learned "
                   "part may be wrong (see the card's shape views)")
    vote = card.get("vote_scale") or {}
    if vote.get("mismatch"):
        off = vote["off_edge"]
        voted = (f"their labels are voted within depth superpixels (scale {vote['scale']}) to "
                 "follow the frames' edges" if vote["scale"] else
                 "no superpixel vote cost the piles little enough to run")
        out.append(f"the labels' boundaries leave the frames' height edges {off['frames']:.3f} "
                   f"of the time, against {off['piles']:.3f} on the model's own piles: the kept "
                   "template is not the part's shape (see template_family.png), and the centre "
                   f"votes cut across parts; {voted}. Check the segmentations (qualitative.png) "
                   "before use, or try `inseggan loop --centre-teacher pasted` (centre votes "
                   "taught on piles pasted from the parts seen whole in your frames: no "
                   "template) or `--families` with one family named")
    fg = _best_foreground_iou(card)
    if fg is not None and fg < MIN_FOREGROUND_IOU:
        out.append(f"foreground IoU {fg:.3f} < {MIN_FOREGROUND_IOU} at every tau: the model's "
                   "renders and the frames' parts do not overlap; check the bin region and "
                   "floor (`inseggan check`)")
    return out


def verdict(card: dict) -> dict:
    """{"ok": bool, "problems": [...]} for the card's "verdict" entry."""
    found = problems(card)
    return {"ok": not found, "problems": found}
