"""A user's frames and the simulated piles made to match them: a recording as the loop's
frames (`BagFrames`), the model file a folder names, and the scene and cut of the piles."""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from inseggan_ros.sim.scene import SceneConfig


@dataclass(frozen=True)
class BagFrames:
    """A user's recording as the loop's frames: a rosbag2 bag (MCAP or sqlite3) of depth images
    with a sensor_msgs/CameraInfo beside them, no labels needed."""

    path: Path
    instances: int  # parts in the bin: the simulated piles hold this many
    topic: str | None = None  # the depth topic (None: the bag's only depth topic)
    labels_topic: str | None = None  # a label image topic, for the card's mIoU rows only
    noise: str = "auto"  # the piles' sensor noise: "auto", measured on the bag's own frames
    # (`sim.noise_fit`), or a preset (`sim.noise`)
    held_out: float = 0.2  # the last fraction of the frames: the card's, nothing else's

    def __post_init__(self):
        from inseggan_ros.sim.noise import NOISE_PRESETS

        if not 1 <= self.instances <= 20:
            raise ValueError(f"instances {self.instances!r} invalid; valid: 1..20 (the parts "
                             "in the bin)")
        if self.noise != "auto" and self.noise not in NOISE_PRESETS:
            raise ValueError(f"noise {self.noise!r} invalid; valid: auto (measured on the "
                             f"bag's frames), {', '.join(NOISE_PRESETS)}")
        if not 0 < self.held_out < 1:
            raise ValueError(f"held_out {self.held_out!r} invalid; valid: between 0 and 1")
        object.__setattr__(self, "path", Path(self.path))
        object.__setattr__(self, "_read", {})  # prep -> the bag's frames: read once a run

    def frames(self, prep, limit: int | None = None) -> tuple[dict, dict]:
        """(the frames before the held-out cut, the held-out ones), preprocessed with `prep`
        (`data.load_bag`; labels only from `labels_topic`); each at most `limit`, spread
        evenly (`selfcheck.split_held_out`, as `modelcard.export_from_bag` takes them). The
        bag is read once per `prep`; each call gets copies."""
        from inseggan_ros.evaluation import selfcheck

        if prep not in self._read:
            self._read[prep] = selfcheck.load_bag_frames(self.path, prep, self.topic,
                                                         self.labels_topic)
        frames = self._read[prep]
        before, held = selfcheck.split_held_out(frames, self.held_out, limit)
        if len(before["x"]) < 2:
            raise ValueError(f"{self.path}: {len(frames['x'])} frames are too few; valid: "
                             f"enough that the last {100 * self.held_out:.0f} % (held out) is a "
                             "frame or more and two or more are left to learn from")
        return before, held

    def scene(self, part) -> "SceneConfig":
        """The simulator's scene: `part` piled `instances` times in the bin the bag shows, seen
        by the camera its frames and CameraInfo give, with the noise its frames show (or the
        preset named)."""
        from dataclasses import replace

        from inseggan_ros.sim.noise import get_noise
        from inseggan_ros.sim.scene import SceneConfig
        from inseggan_ros.sim.user_camera import camera_from_bag

        cam, est, _ = camera_from_bag(self.path, self.topic)
        noise = est["noise"] if self.noise == "auto" else get_noise(self.noise)
        scene = SceneConfig(object=str(part), instances=self.instances, camera=cam, noise=noise)
        return replace(scene, bin=replace(scene.bin, inner_size=tuple(est["bin_inner_size"])))

    def describe(self) -> dict:
        return {"kind": "bag", **{k: str(v) if isinstance(v, Path) else v
                                  for k, v in asdict(self).items()}}


def _model_file(model) -> Path:
    path = Path(model)
    file = path / "model.pt" if path.is_dir() else path
    if not file.is_file():
        raise ValueError(f"{model}: no model there; valid: a model folder with model.pt, or a "
                         ".pt checkpoint (`inseggan train`'s best.pt)")
    return file


def _same_view(file: Path, data) -> None:
    """The model's template is in units of its training crop: the user's frames must be cut
    and scaled the same way (same camera and bin), else the simulated part and the template
    disagree in size."""
    from inseggan_ros.core import checkpoint
    from inseggan_ros.data.datasets import sim_preprocess_config

    trained = checkpoint.load(file).get("preprocess_config") or {}
    user = sim_preprocess_config(data).to_dict()
    keys = ("roi", "floor_depth", "floor_plane", "max_height", "size")
    diff = {k: (trained.get(k), user.get(k)) for k in keys
            if k in user and _as_list(trained.get(k)) != _as_list(user.get(k))}
    if diff:
        raise ValueError(f"{data}: its frames are not cut as the model's were "
                         + ", ".join(f"{k} {a} (model) vs {b} (data)" for k, (a, b) in diff.items())
                         + "; valid: the data set of the camera and bin the model was trained on")


def _as_list(v):
    return [round(float(e), 6) for e in v] if isinstance(v, (list, tuple)) else v


def pile_scene(data, meta: dict | None, part) -> "SceneConfig":
    """The simulator's scene for piles of `part` as the user's frames were taken: a data set's
    own scene (`meta`, its meta.json) with the part swapped, or (`meta` None) the bin and
    camera a bag's frames give (`BagFrames.scene`)."""
    from inseggan_ros.sim.scene import SceneConfig

    if meta is None:
        return data.scene(part)
    return SceneConfig.from_dict({**meta["scene"], "object": str(part)})


def pile_view(data, state: dict) -> dict:
    """How simulated piles are cut (`data.load_sim_split` keywords): as a data set's frames,
    with its known bin and floor ({}), or for a bag as the model (checkpoint `state`) cuts
    the bag's frames."""
    from inseggan_ros.runtime.preprocess import PreprocessConfig

    if not isinstance(data, BagFrames):
        return {}
    return {"cfg": PreprocessConfig.from_dict(state["preprocess_config"]), "as_given": True}
