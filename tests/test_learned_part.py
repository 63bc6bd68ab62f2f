"""A learned template as a simulator part (`sim.learned`): it drops and settles in the bin, and
the simulator's depth camera sees it as the model itself renders it."""
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from inseggan_ros.core.checkpoint import load
from inseggan_ros.runtime.model import build_models
from inseggan_ros.sim.camera import CameraConfig
from inseggan_ros.sim.learned import model_camera, template_object, template_origin, template_scale
from inseggan_ros.sim.objects import get_object
from inseggan_ros.sim.scene import BinSimulator, SceneConfig

MODELS = Path(__file__).resolve().parents[1] / "models"


def _model_render(model: Path, pose7: np.ndarray, cam) -> tuple[np.ndarray, np.ndarray]:
    """The model's own render of its template at the simulator's pose `pose7` (x, y, z,
    quaternion of the exported body), seen by the nearly orthographic camera `cam` (looking
    straight down): -> where the render rises above the preprocessing's min_height (the soft
    silhouette has a tail), and the window of the camera's image it covers (x0, y0, x1, y1),
    whose pixels are the render's."""
    state = load(model / "model.pt")
    G = build_models(state, model / "model.pt")[1].eval()
    scale = template_scale(state, G, model_camera(model / "model.pt"))  # as exported
    R = Rotation.from_quat(pose7[3:]).as_matrix()
    origin = R @ template_origin(model) + pose7[:3]  # the template frame's origin, world
    # world -> model axes: image x to the right, image y down (signs from the camera itself)
    u, v = cam.project(np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]])).T
    F = np.diag([np.sign(u[1] - u[0]), np.sign(v[2] - v[0]), 1.0])
    # a window of the image centred on the part, 2 template units (2 * scale metres) wide
    half = int(round(scale[0] * cam.fx / cam.to_camera(origin[None])[0, 2]))
    (uc, vc), = cam.project(origin[None])
    x0, y0 = int(round(uc)) - half, int(round(vc)) - half
    # pixel i spans [i - 0.5, i + 0.5) in the camera's coordinates, [i, i + 1) in the render's
    t = [(uc + 0.5 - x0) / (2 * half) * 2 - 1, (vc + 0.5 - y0) / (2 * half) * 2 - 1,
         origin[2] / scale[2] - float(G.lift.detach())]
    rotvec = Rotation.from_matrix(F @ R @ F).as_rotvec()
    pose = torch.tensor(np.r_[rotvec, t], dtype=torch.float32)
    with torch.no_grad():
        r = G.render_poses(pose.view(1, 1, 6), size=2 * half)[0, 0].numpy()
    prep = state["preprocess_config"]
    return r > -1 + 2 * prep["min_height"] / prep["max_height"], (x0, y0, x0 + 2 * half,
                                                                  y0 + 2 * half)


def test_exported_template_is_convex_pieces_at_learned_size():
    spec = template_object(MODELS / "cylinder")
    assert len(spec.parts) >= 1 and spec.mass > 0
    for part in spec.parts:  # each piece is a convex body with volume
        assert ConvexHull(part).volume > 0
    assert spec.mesh.triangles.max() < len(spec.mesh.vertices)
    # the learned rod is a rod: longer than it is wide, at the size of the part it learned
    # (the true cylinder is 40 x 24 x 24 mm; the learned one is within a factor of 1.6 of it)
    length, width = np.sort(spec.extent)[::-1][:2]
    assert length > 1.2 * width
    true = np.sort(get_object("cylinder").extent)[::-1]
    assert np.all(np.sort(spec.extent)[::-1] / true < 1.6)
    assert np.all(np.sort(spec.extent)[::-1] / true > 1 / 1.6)
    assert get_object(str(MODELS / "cylinder")).extent.tolist() == spec.extent.tolist()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_exported_body_settles_and_renders_like_the_model(seed):
    model = MODELS / "cylinder"
    # the model renders orthographically: the camera here is 10 times as far as the default
    # one, so that it sees the body nearly orthographically too (at 0.35 m a part's top looks
    # several per cent larger than its foot, and its sides show off the optical axis), with
    # pixels a third of the default's on the floor, so that a pixel's rim around a part of about
    # 50 pixels does not hide how well the shapes agree
    cam = CameraConfig(width=448, height=448, fx=12600.0, fy=12600.0, cx=223.5, cy=223.5,
                       mount_height=3.5, near=3.0, far=4.0)
    cfg = SceneConfig(object=str(model), instances=1, camera=cam)
    with BinSimulator(cfg) as sim:
        scene = sim.render(seed)
    spec = get_object(str(model))
    R = Rotation.from_quat(scene.poses[0, 3:]).as_matrix()
    lowest = min(float((part @ R.T + scene.poses[0, :3])[:, 2].min()) for part in spec.parts)
    assert abs(lowest) < 0.002, f"the body rests {lowest * 1000:.1f} mm from the floor"
    assert set(np.unique(scene.labels)) == {0, 1}
    mine, (x0, y0, x1, y1) = _model_render(model, scene.poses[0].astype(float), cam)
    heights = cam.mount_height - scene.depth[y0:y1, x0:x1]  # the camera looks down
    seen = (heights > load(model / "model.pt")["preprocess_config"]["min_height"]) \
        & (scene.labels[y0:y1, x0:x1] == 1)  # not the bin's walls
    iou = (mine & seen).sum() / (mine | seen).sum()
    assert iou > 0.95, f"IoU of the simulator's and the model's silhouettes {iou:.3f}"
