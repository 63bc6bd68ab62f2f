"""Where the package's shipped files are: models/, bags/ and config/ under share/inseggan_ros
when installed through ament (colcon), else beside the source tree. No ROS imports beyond
ament_index_python, which is optional: a plain checkout works too."""
from __future__ import annotations

from pathlib import Path

PACKAGE = "inseggan_ros"
DEFAULT_MODEL = "cylinder"  # models/<name>/model.pt, the node's and the demo's default


class NotFoundError(ValueError):
    """A name that is neither a path nor a shipped file; the message lists the valid names."""


def shipped_dir(kind: str) -> Path | None:
    """share/inseggan_ros/<kind> ('models', 'bags', 'config'), or the source tree's <kind>/."""
    try:
        from ament_index_python.packages import get_package_share_directory

        share = Path(get_package_share_directory(PACKAGE)) / kind
        if share.is_dir():
            return share
    except Exception:  # not installed through ament (or ament_index_python absent)
        pass
    here = Path(__file__).resolve().parents[2] / kind
    return here if here.is_dir() else None


def _names(folder: Path | None, keep=lambda p: True) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if keep(p)) if folder else []


def resolve_model(path: str, what: str = "model_path") -> Path:
    """'' = the default shipped model; a shipped model's name; a model folder (its model.pt);
    or a checkpoint path."""
    name = path or DEFAULT_MODEL
    p = Path(name).expanduser()
    if p.is_dir() and (p / "model.pt").is_file():  # models/<name>/, or the loop's out/model
        return p / "model.pt"
    if p.is_file() or p.is_absolute() or "/" in name or name.endswith(".pt"):
        return p
    shipped = shipped_dir("models")
    if shipped and (shipped / name / "model.pt").is_file():
        return shipped / name / "model.pt"
    names = _names(shipped, lambda x: (x / "model.pt").is_file())
    raise NotFoundError(f"{what} {path!r}: no such model file or shipped model; shipped "
                        f"models: {', '.join(names) or 'none'}")


def resolve_bag(path: str, what: str = "bag_path") -> Path:
    """A bag path, or the name of a bag shipped in the package's bags/ folder."""
    p = Path(path).expanduser()
    if p.exists() or p.is_absolute() or "/" in path:
        return p
    shipped = shipped_dir("bags")
    if shipped and (shipped / path).exists():
        return shipped / path
    raise NotFoundError(f"{what} {path!r}: no such bag; shipped bags: "
                        f"{', '.join(_names(shipped)) or 'none'}")


def resolve_config(name: str) -> Path:
    """A settings/parameters file path, or the name of one shipped in config/ ('realtime')."""
    p = Path(name).expanduser()
    if p.is_file() or "/" in name:
        return p
    shipped = shipped_dir("config")
    for candidate in (name, f"{name}.yaml"):
        if shipped and (shipped / candidate).is_file():
            return shipped / candidate
    raise NotFoundError(f"settings file {name!r}: no such file or shipped config; shipped: "
                        f"{', '.join(_names(shipped)) or 'none'}")
