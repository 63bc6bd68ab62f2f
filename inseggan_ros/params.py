"""The segmenter's test-time settings in ROS 2 parameter files (config/realtime.yaml,
config/quality.yaml): read without ROS, so that `inseggan export`, `inseggan eval` and the
benchmark apply a file exactly as the node does.

    /**/segmenter:          # the segmenter node in any namespace
      ros__parameters:
        refine_steps: 48
        ...
"""
from __future__ import annotations

from pathlib import Path

# node parameter -> InferenceConfig field (smoothing ones: SmoothConfig fields)
SETTINGS = {"refine_steps": "refine_steps", "refine_hypotheses": "hypotheses",
            "refine_keep": "keep", "smooth_iters": "iters",
            "smooth_full_res_iters": "full_res_iters", "encoder_precision": "precision"}
# node parameter -> the command-line flag's argparse name (`inseggan eval/export`, bench_node)
FLAGS = {"refine_steps": "refine_steps", "refine_hypotheses": "hypotheses", "refine_keep": "keep",
         "smooth_iters": "smooth_iters", "smooth_full_res_iters": "full_res_smooth_iters",
         "encoder_precision": "precision"}


def from_flags(args) -> dict:
    """The node parameters that command-line flags set (flags left unset are absent)."""
    return {name: getattr(args, flag) for name, flag in FLAGS.items()
            if getattr(args, flag) is not None}


def read_params_file(path) -> dict:
    """The segmenter's parameters in a ROS 2 parameters file (its `/**`, then `segmenter`,
    `/segmenter` or `/**/segmenter` section). Raises ValueError naming the file when it is not
    one."""
    import yaml

    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as e:
        raise ValueError(f"{path}: not a readable parameters file ({e})") from None
    out = {}
    for node in ("/**", "segmenter", "/segmenter", "/**/segmenter"):
        section = doc.get(node) if isinstance(doc, dict) else None
        if isinstance(section, dict):
            out.update(section.get("ros__parameters") or {})
    if not out:
        raise ValueError(f"{path}: no `/**/segmenter: ros__parameters:` section")
    return out


def apply(cfg, params: dict):
    """InferenceConfig `cfg` with the test-time node parameters in `params` applied (the rest
    of `params` is ignored)."""
    from dataclasses import replace

    top = {SETTINGS[k]: str(v) if k == "encoder_precision" else int(v)
           for k, v in params.items() if k in SETTINGS and not k.startswith("smooth")}
    cfg = replace(cfg, **top)
    return cfg.with_smoothing(params.get("smooth_iters"), params.get("smooth_full_res_iters"))
