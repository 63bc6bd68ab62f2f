"""Test-time settings: how a trained model segments (`InferenceConfig`, `SmoothConfig`).

A shipped model stores its settings; the segmenter node's parameters, the `inseggan`
command-line flags and ROS 2 parameter files (config/realtime.yaml) override them. Each setting
has ONE name everywhere: the field's name (a `SmoothConfig` field inside `InferenceConfig.smooth`
is `smooth_<field>`), which is also the node parameter and, with dashes, the flag:

    InferenceConfig.refine_hypotheses  <->  -p refine_hypotheses:=8  <->  --refine-hypotheses 8
    InferenceConfig.smooth.iters       <->  -p smooth_iters:=5       <->  --smooth-iters 5

The fields that carry a `doc` in their metadata are the exposed ones (`exposed()`); the node
declares its parameters and the command line its flags from that list. No torch here, so that
argument parsers and parameter files load fast.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

# The encoder's arithmetic: float32, bfloat16 (faster where the CPU or GPU computes it natively,
# e.g. AVX512-BF16), or auto: bfloat16 where native, else float32 (emulated bfloat16 is slower).
PRECISIONS = ("float32", "bfloat16", "auto")
# Where the labels come from: the label head (`label_head.py`) or the z-buffer alone.
LABEL_HEAD = ("on", "off")
# Whether the labels come from the model's centre votes (`centres.py`) instead.
CENTRE_VOTES = ("on", "off")


def _doc(text: str, lo: int | None = None, hi: int | None = None,
         choices: tuple[str, ...] | None = None) -> dict:
    return {"doc": text, "range": (lo, hi), "choices": choices}


@dataclass(frozen=True)
class SmoothConfig:
    """Depth-aware smoothing of the z-buffered labels (`smoothing.py`): mean-field inference in
    a fully connected CRF (Kraehenbuehl and Koltun 2011) restricted to a (2 radius + 1)^2
    window. The unary term is the model's label (weight 1), the pairwise term a Potts reward for
    agreeing with neighbours of similar height, weight * exp(-dh^2 / 2 sigma_height^2 - dp^2 /
    2 sigma_px^2). Labels then follow the input's height edges instead of the 64 x 64 render's.
    Heights are the model input's units ([-1, 1] over max_height); distances in model pixels."""

    iters: int = field(default=20, metadata=_doc(
        "iterations of depth-aware label smoothing at the model's 64 x 64 (0 = off, also at "
        "full resolution)", 0, 200))
    radius: int = 4
    sigma_height: float = 0.2
    sigma_px: float = 2.5
    weight: float = 3.0
    full_res_iters: int = field(default=10, metadata=_doc(
        "then iterations at the input's resolution near instance boundaries (0 = off)", 0, 200))

    @property
    def full_res_active(self) -> int:
        """The full-resolution iterations that run: none when smoothing is off."""
        return self.full_res_iters if self.iters else 0

    def __post_init__(self):
        for name, ok, valid in (("iters", self.iters >= 0, ">= 0"),
                                ("full_res_iters", self.full_res_iters >= 0, ">= 0"),
                                ("radius", self.radius >= 1, ">= 1"),
                                ("sigma_height", self.sigma_height > 0, "> 0"),
                                ("sigma_px", self.sigma_px > 0, "> 0"),
                                ("weight", self.weight >= 0, ">= 0")):
            if not ok:
                raise ValueError(f"smooth_{name} {getattr(self, name)!r} invalid; "
                                 f"valid: {valid}")


@dataclass(frozen=True, kw_only=True)  # by name only: settings are added over time
class InferenceConfig:
    """How a model segments at test time (`segment.Segmenter`): the pose fit from several
    starting points (`refine.py`), label smoothing, the encoder's arithmetic."""

    refine_steps: int = field(default=0, metadata=_doc(
        "test-time refinement of the poses: Levenberg-Marquardt iterations per frame (0 = the "
        "best-fitting starting poses as they are)", 0, 500))
    refine_hypotheses: int = field(default=1, metadata=_doc(
        "starting points: the encoder's poses, those on the mirrored and transposed inputs (up "
        "to 8), then jittered ones; the best-fitting is kept", 1, 32))
    refine_keep: int = field(default=0, metadata=_doc(
        "how many of the starting points, the best-fitting first, are refined (0 = all; the "
        "refinement's time grows about in proportion)", 0, 32))
    refine_swaps: int = field(default=0, metadata=_doc(
        "where the best-fitting starting point is chosen, up to this many single instances of "
        "the other starting points swapped into it, each where it explains the input better "
        "(with refine_keep 1 before the refinement, else after it; 0 = off)", 0, 16))
    smooth: SmoothConfig = SmoothConfig(iters=0)
    encoder_precision: str = field(default="float32", metadata=_doc(
        "the encoder's arithmetic: float32, bfloat16, or auto (bfloat16 where the CPU or GPU "
        "computes it natively, else float32)", choices=PRECISIONS))
    superpixel_scale: int = field(default=0, metadata=_doc(
        "the labels voted within depth superpixels (superpixels.py): Felzenszwalb's graph "
        "segmentation of the 64 x 64 heights at this scale (smaller: finer superpixels), each "
        "superpixel given its most frequent label (0 = off)", 0, 10000))
    split_scale: int = field(default=0, metadata=_doc(
        "then parts the model missed found again (superpixels.py): a label that spans several "
        "segments of the heights at this coarse scale, or several regions, gives its second "
        "piece an unused id or one that labels fewer pixels (0 = off)", 0, 10000))
    label_head: str = field(default="off", metadata=_doc(
        "the labels from the model's label head (on: each pixel moved to the instance the head "
        "scores highest, given the input and the renders; models without a head: off) or "
        "straight from the z-buffer (off)", choices=LABEL_HEAD))
    centre_votes: str = field(default="off", metadata=_doc(
        "the instances from the model's centre votes (on: a small network's heatmap of part "
        "centres and each pixel's offset to its part's centre, each instance given the id of "
        "the render it overlaps most; then smoothing, the vote only at "
        "centre_superpixel_scale, and split; models without the network: off) or from the "
        "z-buffer (off)", choices=CENTRE_VOTES))
    centre_precision: str = field(default="float32", metadata=_doc(
        "the centre-vote network's arithmetic (its last layer always float32): float32, "
        "bfloat16, or auto (bfloat16 where the CPU or GPU computes it natively, else float32); "
        "a model stores the one its validation split chose", choices=PRECISIONS))
    centre_superpixel_scale: int = field(default=0, metadata=_doc(
        "with centre votes on, their labels voted within depth superpixels of this scale as "
        "superpixel_scale votes the z-buffer's (0 = off): `inseggan loop` sets it where the "
        "labels cross the frames' height edges far more often than its own piles' "
        "(evaluation/vote_scale.py)", 0, 10000))

    def __post_init__(self):
        for name, ok, valid in (
                ("refine_steps", self.refine_steps >= 0, ">= 0"),
                ("refine_hypotheses", self.refine_hypotheses >= 1, ">= 1"),
                ("refine_keep", self.refine_keep >= 0, ">= 0 (0 = all starting points)"),
                ("refine_swaps", self.refine_swaps >= 0, ">= 0 (0 = off)"),
                ("superpixel_scale", self.superpixel_scale >= 0, ">= 0 (0 = off)"),
                ("split_scale", self.split_scale >= 0, ">= 0 (0 = off)"),
                ("centre_superpixel_scale", self.centre_superpixel_scale >= 0,
                 ">= 0 (0 = off)"),
                ("encoder_precision", self.encoder_precision in PRECISIONS,
                 ", ".join(PRECISIONS)),
                ("label_head", self.label_head in LABEL_HEAD, ", ".join(LABEL_HEAD)),
                ("centre_votes", self.centre_votes in CENTRE_VOTES, ", ".join(CENTRE_VOTES)),
                ("centre_precision", self.centre_precision in PRECISIONS,
                 ", ".join(PRECISIONS))):
            if not ok:
                raise ValueError(f"{name} {getattr(self, name)!r} invalid; valid: {valid}")
        if self.label_head == "on" and self.centre_votes == "on":
            raise ValueError("label_head on and centre_votes on: the labels come from one of "
                             "them; valid: at most one on")

    @property
    def vote_scale(self) -> int:
        """The superpixel vote's scale these settings run: over centre votes their own,
        `centre_superpixel_scale`, off unless set (their labels already follow the heights
        where the model's part is the frames': the vote lowered the cylinder's and every shipped
        tilted model's, docs/experiments.md)."""
        return self.centre_superpixel_scale if self.centre_votes == "on" \
            else self.superpixel_scale

    def to_dict(self) -> dict:
        return {**{f.name: getattr(self, f.name) for f in fields(self) if f.name != "smooth"},
                "smooth": asdict(self.smooth)}

    @staticmethod
    def from_dict(d: dict) -> "InferenceConfig":
        """From a checkpoint's "inference" record. Models exported before the settings had one
        name each store hypotheses, keep and precision; older ones lack smoothing."""
        old = {"hypotheses": "refine_hypotheses", "keep": "refine_keep",
               "precision": "encoder_precision"}
        d = {old.get(k, k): v for k, v in d.items()}
        unknown = set(d) - {f.name for f in fields(InferenceConfig)}
        if unknown:
            raise ValueError(f"unknown inference settings {sorted(unknown)}")
        smooth = SmoothConfig(**d.pop("smooth", {"iters": 0}))
        return InferenceConfig(**d, smooth=smooth)


@dataclass(frozen=True)
class Setting:
    """One exposed setting: its name (field, node parameter, flag), type and documentation."""

    name: str
    type: type
    doc: str
    range: tuple[int | None, int | None]
    choices: tuple[str, ...] | None

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")


def _leaves(cls, prefix: str = ""):
    for f in fields(cls):
        if f.name == "smooth":
            yield from _leaves(SmoothConfig, "smooth_")
        elif "doc" in f.metadata:
            yield prefix, f


def exposed() -> list[Setting]:
    """The settings the node and the command line expose, in declaration order."""
    types = {"int": int, "str": str, "float": float}
    return [Setting(prefix + f.name, types.get(f.type, f.type) if isinstance(f.type, str)
                    else f.type, f.metadata["doc"], f.metadata["range"], f.metadata["choices"])
            for prefix, f in _leaves(InferenceConfig)]


def values(cfg: InferenceConfig) -> dict:
    """{setting name: its value in `cfg`} for every exposed setting."""
    out = {}
    for s in exposed():
        if s.name.startswith("smooth_"):
            out[s.name] = getattr(cfg.smooth, s.name[len("smooth_"):])
        else:
            out[s.name] = getattr(cfg, s.name)
    return out


def apply(cfg: InferenceConfig, params: dict) -> InferenceConfig:
    """`cfg` with the settings named in `params` applied (other keys, such as the node's
    non-inference parameters, are ignored). Raises ValueError naming a bad value."""
    names = {s.name: s for s in exposed()}
    top, smooth = {}, {}
    for key, value in params.items():
        if key not in names or value is None:
            continue
        value = names[key].type(value)
        if key.startswith("smooth_"):
            smooth[key[len("smooth_"):]] = value
        else:
            top[key] = value
    return replace(cfg, **top, smooth=replace(cfg.smooth, **smooth))


def add_flags(parser, default: str) -> None:
    """The exposed settings as command-line flags (`default`: what an unset flag means), plus
    --profile, a segmenter parameters file the flags override."""
    parser.add_argument("--profile", type=Path,
                        help="segmenter parameters file: a path, or a shipped one's name "
                             "(realtime, quality, fastest, d435) " + default)
    for s in exposed():
        parser.add_argument(s.flag, type=s.type, choices=s.choices, default=None,
                            help=f"{s.doc} {default}")


def from_flags(args) -> dict:
    """{setting name: value} of the flags given on the command line (unset flags are absent)."""
    return {s.name: getattr(args, s.name) for s in exposed()
            if getattr(args, s.name, None) is not None}


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


def file_base(cfg: InferenceConfig, stored: bool = True) -> InferenceConfig:
    """What a parameters file applies to: a model's own settings, or, for a checkpoint that
    stores none (a training checkpoint), realtime.yaml's, from which every exported model
    starts. So a file that leaves a setting to the model (quality.yaml leaves the vote's and
    the split's scales) means the same for both; over the bare built-in defaults it would turn
    the vote and the split off."""
    if stored:
        return cfg
    from inseggan_ros.core.paths import resolve_config

    return apply(cfg, read_params_file(resolve_config("realtime")))


def apply_file(cfg: InferenceConfig, name, stored: bool = True) -> InferenceConfig:
    """The parameters file `name` (a path, or a shipped one's name: "quality") applied to
    `file_base(cfg, stored)`."""
    from inseggan_ros.core.paths import resolve_config

    return apply(file_base(cfg, stored), read_params_file(resolve_config(str(name))))


def resolve(base: InferenceConfig, args, stored: bool = True) -> InferenceConfig:
    """`base`, then the --profile parameters file, then the explicit flags (`add_flags`).
    `stored`: whether `base` is settings a model stores; if not (a training checkpoint's bare
    defaults), a --profile file applies over realtime.yaml's (`file_base`)."""
    profile = getattr(args, "profile", None)
    if profile:
        base = apply_file(base, profile, stored)
    return apply(base, from_flags(args))
