"""The parts made of bars (a flat T, an angle bracket, a flat U, a flat Z): neither solids of
revolution nor boxes; each is dropped into a bin, rendered, and measured as the shape measures
take a part."""
import numpy as np
import pytest

from inseggan_ros.evaluation.shape import components, occupancy, part_pieces, part_voxel, vertices
from inseggan_ros.sim.objects import OBJECTS, get_object
from inseggan_ros.sim.scene import BinSimulator, SceneConfig

# name -> (extent x, y, z in mm, volume in cm^3: the bars' sum less their shared corner)
BAR_PARTS = {"t_piece": ((40, 40, 8), (40 * 10 + 10 * 31 - 10 * 1) * 8 / 1000),
             "l_bracket": ((30, 20, 26), (30 * 20 * 5 + 5 * 20 * 26 - 5 * 20 * 5) / 1000),
             "u_clip": ((36, 36, 6), (36 * 8 + 2 * 8 * 29 - 2 * 8 * 1) * 6 / 1000),
             "z_bracket": ((40, 40, 8), (2 * 24 * 8 + 8 * 26 - 2 * 8 * 1) * 8 / 1000)}


@pytest.mark.parametrize("name", BAR_PARTS)
def test_bar_part_is_in_the_library_at_its_real_size(name):
    spec = get_object(name)
    assert name in OBJECTS
    size, volume_cm3 = BAR_PARTS[name]
    np.testing.assert_allclose(spec.extent * 1000, size, atol=1e-6)
    assert len(spec.parts) >= 2  # a union of convex pieces, not one convex body
    # the origin at the centre of mass: the mean of voxel centres inside the union
    pieces = part_pieces(name)
    voxel = 0.0005
    lo, hi = vertices(pieces).min(0), vertices(pieces).max(0)
    axes = [np.arange(a + voxel / 2, b, voxel) for a, b in zip(lo, hi)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = occupancy(pieces, points)
    assert inside.sum() * voxel ** 3 * 1e6 == pytest.approx(volume_cm3, rel=0.03)
    assert np.abs(points[inside].mean(0)).max() < 0.0005
    density = spec.mass / (volume_cm3 * 1e-6)
    assert 2000 < density < 8000  # aluminium or steel


@pytest.mark.parametrize("name", BAR_PARTS)
def test_bar_part_shape_measures(name):
    pieces = part_pieces(name)
    assert len(pieces) == len(get_object(name).parts)
    assert components(pieces) == 1, "the bars overlap: one body, not bars that touch"
    largest = max(BAR_PARTS[name][0]) / 1000
    assert part_voxel(name) == pytest.approx(largest / 30)
    assert part_voxel(name, voxels=60) == pytest.approx(largest / 60)
    # neither a box nor a solid of revolution: its bounding box is far from full
    assert BAR_PARTS[name][1] * 1e-6 < 0.6 * np.prod(np.ptp(vertices(pieces), axis=0))


@pytest.mark.parametrize("name", BAR_PARTS)
def test_bar_part_drops_into_a_bin_and_renders(name):
    cfg = SceneConfig(object=name, instances=4)
    with BinSimulator(cfg) as sim:
        scenes = [sim.render(seed) for seed in (0, 1)]
    half = np.asarray(cfg.bin.inner_size) / 2
    for scene in scenes:
        assert scene.poses.shape == (4, 7)
        assert (np.abs(scene.poses[:, :2]) < half).all()
        assert set(np.unique(scene.labels)) == {0, 1, 2, 3, 4}  # every part dropped is seen
        obj = scene.depth[scene.labels > 0]
        assert (obj < cfg.camera.mount_height - 0.002).mean() > 0.95  # above the floor
        # in the pile, not hovering: no higher than the walls and a part on top of them
        assert obj.min() > cfg.camera.mount_height - cfg.bin.wall_height - max(
            get_object(name).extent)


def test_a_compound_part_s_files_are_shared_and_left_nowhere_else(tmp_path, monkeypatch):
    """A compound part's pieces go to pybullet as mesh files: one folder per part, named by its
    content, shared by every simulator of it; a simulator made and closed leaves no folder of
    its own (pool workers end without finalisers, so a folder each piled up in the temp dir);
    folders unused for a day are removed when another part's is made."""
    import os
    import tempfile
    import time

    from inseggan_ros.sim.scene import PARTS_DIR, PARTS_KEEP_S, part_files

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    parts = get_object("u_clip").parts
    first = part_files(parts)
    assert part_files(parts) == first and len(first) == len(parts)
    assert len({p.rsplit("/", 1)[0] for p in first}) == 1
    with open(first[0]) as f:
        assert sum(line.startswith("v ") for line in f) == len(parts[0])
    assert part_files(get_object("z_bracket").parts)[0].rsplit("/", 1)[0] != \
        first[0].rsplit("/", 1)[0]
    before = set(tmp_path.rglob("*"))
    with BinSimulator(SceneConfig(object="u_clip", instances=2)) as sim:
        sim.render(0)
    assert set(tmp_path.rglob("*")) == before
    old = time.time() - 2 * PARTS_KEEP_S  # unused for two days: removed when a part is made
    os.utime(first[0].rsplit("/", 1)[0], (old, old))
    part_files(get_object("t_piece").parts)
    assert not os.path.exists(first[0]) and len(list((tmp_path / PARTS_DIR).iterdir())) == 2
