"""Issue 25 through the Python API: the plausibility of sparse maps (units) against the image and
K, K's field of view and the inverted-transform test (oracle: the synthetic street, the docs/example
rig and, where present, the shared KITTI frames, whose statistics are in the docstrings of
crfdepth.plausibility.check_sparse_plausible and crfdepth.inputs.points_to_sparse)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from crfdepth.api import check_frame, complete_depth
from crfdepth.data.synthetic import make_scene
from crfdepth.errors import InputError
from crfdepth.geometry.projection import ground_normal, ground_tilt_deg, keep_every_ring
from crfdepth.inputs import points_to_sparse
from crfdepth.intrinsics import check_intrinsics
from crfdepth.io.calibration import RigCalibration, load_any_calibration
from crfdepth.io.kitti import read_velodyne
from crfdepth.output import CRFOutput
from crfdepth.plausibility import check_sparse_plausible


@pytest.fixture(scope="module")
def scenes():
    return [make_scene(seed, height=176, width=608, beams=beams) for seed in (0, 3) for beams in (64, 16)]


def test_synthetic_scenes_pass_in_metres_and_fail_in_other_units(scenes):
    for scene in scenes:
        check_frame(scene.image, scene.sparse, scene.K)
        with pytest.raises(InputError, match=r"^sparse: .*that looks like millimetres: divide by 1000$"):
            check_frame(scene.image, scene.sparse * 1000, scene.K)
        with pytest.raises(InputError, match=r"^sparse: .*that looks like centimetres: divide by 100"):
            check_frame(scene.image, scene.sparse * 100, scene.K)
        with pytest.raises(InputError, match=r"^sparse: .*that looks like the raw codes of a KITTI depth PNG"):
            check_frame(scene.image, np.round(scene.sparse * 256).astype(np.uint16), scene.K)


def test_millimetre_png_read_as_kitti_is_refused_by_the_ground_below_the_camera(scenes):
    """A millimetre PNG through read_depth_png is 3.9x too deep: the ground 6.4 m below the camera."""
    for scene in scenes:
        with pytest.raises(InputError, match=r"^sparse: expected depth in metres \(.*\); that looks like a "
                                             r"millimetre PNG read as a KITTI PNG"):
            check_frame(scene.image, scene.sparse * 1000 / 256, scene.K)


def test_plain_metres_read_as_kitti_is_refused(scenes):
    scene = scenes[0]
    with pytest.raises(InputError, match=r"nearer than 1 m\), got 100% of them .*a PNG of whole metres read as a "
                                         r"KITTI PNG"):
        check_frame(scene.image, scene.sparse / 256, scene.K)


def test_check_sparse_plausible_without_K_ranks_by_the_median():
    depth = np.zeros((40, 60))
    depth[::4, ::4] = np.linspace(5, 30, depth[::4, ::4].size).reshape(10, 15)
    check_sparse_plausible("sparse", depth)
    with pytest.raises(InputError, match=r"beyond 200 m\), got "):
        check_sparse_plausible("sparse", depth * 10)


def test_field_of_view_bounds():
    with pytest.raises(InputError, match=r"^K: expected a field of view below 170 degrees over the 1242x375 .*, got "
                                         r"179\.3 x 177\.6 degrees"):
        check_intrinsics([[4, 0, 621], [0, 4, 187], [0, 0, 1]], "K", (375, 1242))
    with pytest.raises(InputError, match=r"^K: expected a field of view above 1 degree"):
        check_intrinsics([[20000, 0, 8], [0, 20000, 4], [0, 0, 1]], "K", (9, 17))
    check_intrinsics([[300, 0, 621], [0, 300, 187], [0, 0, 1]], "K", (375, 1242))  # 128 degrees: a wide lens


def _inverted_refused(points, rig, size):
    """The right transform passes, its inverse is refused naming the angles; trusted it projects."""
    inverted = RigCalibration(rig.K, np.linalg.inv(rig.T_cam_lidar), source="rig.yaml")
    points_to_sparse(points, rig, size)
    with pytest.raises(InputError, match=r"^T_cam_lidar \(rig.yaml\): .*looks inverted: it turns the scan's ground "
                                         r"plane (8[5-9]|9[0-5]) degrees from level"):
        points_to_sparse(points, inverted, size)
    assert (points_to_sparse(points, inverted, size, trust_transform=True) > 0).any()


def test_inverted_transform_on_synthetic_and_example(scenes):
    for scene in scenes:
        _inverted_refused(scene.points, RigCalibration(scene.K, scene.T_cam_lidar), scene.sparse.shape)
    from pathlib import Path

    from crfdepth.io.pointcloud import read_points
    example = Path(__file__).resolve().parents[1] / "docs" / "example"
    _inverted_refused(read_points(example / "scan.pcd"), load_any_calibration(example / "rig.yaml"), (480, 640))


@pytest.mark.kitti
def test_inverted_transform_on_real_kitti_scans_64_and_16_beams(kitti_root):
    rig = load_any_calibration(kitti_root / "raw" / "2011_09_26")
    scans = sorted((kitti_root / "raw" / "2011_09_26").glob("*/velodyne_points/data/*.bin"))[:4]
    assert scans
    for scan in scans:
        points = read_velodyne(scan)
        for cloud in (points, keep_every_ring(points, 4)):
            normal = ground_normal(cloud)
            assert ground_tilt_deg(normal, rig.T_cam_lidar) < 5
            assert 85 < ground_tilt_deg(normal, np.linalg.inv(rig.T_cam_lidar)) < 95
            plain = RigCalibration(rig.K, rig.T_cam_lidar, image_size=rig.image_size)  # no exact KITTI chain
            _inverted_refused(cloud, plain, (375, 1242))


@pytest.mark.kitti
def test_real_kitti_sparse_maps_pass_with_their_K(kitti_root):
    from crfdepth.io.kitti import read_depth_png, read_intrinsics, read_rgb
    root = kitti_root / "depth_selection" / "val_selection_cropped"
    for path in sorted((root / "velodyne_raw").glob("*.png")):
        stem = path.name.replace("velodyne_raw", "image")
        K = read_intrinsics(root / "intrinsics" / stem.replace(".png", ".txt"))
        image = read_rgb(root / "image" / stem)
        check_frame(image, read_depth_png(path), K)
        with pytest.raises(InputError, match="millimetre PNG read as a KITTI PNG"):
            check_frame(image, read_depth_png(path) * 1000 / 256, K)


def test_a_camera_up_a_mast_is_refused_by_the_rig_guess_and_accepted_with_trust_units(mast_map):
    sparse, K = mast_map
    image = np.full((*sparse.shape, 3), 128, np.uint8)
    with pytest.raises(InputError, match=r"^sparse: expected depth in metres \(the ground at most 4 m below the "
                                         r"camera .* pass trust_units=True$"):
        complete_depth(image, sparse=sparse, K=K, return_std=False)
    with pytest.raises(InputError, match=r"^trust_units: expected True or False, got 'yes'$"):
        complete_depth(image, sparse=sparse, K=K, trust_units="yes")


def test_a_camera_up_a_mast_passes_the_checks_with_trust_units(monkeypatch, mast_map):
    """trust_units skips only the rig guess: the map reaches the model unchanged."""
    import crfdepth.api as api
    from crfdepth.inference import PIPELINES

    sparse, K = mast_map
    seen = {}

    def fake_pipeline(model, image, sparse_t, K_t, return_std, **_):
        seen["sparse"] = sparse_t[0, 0].numpy()
        return CRFOutput(torch.ones(1, 1, *sparse.shape), *(None,) * 10)

    monkeypatch.setitem(PIPELINES, "pixel", fake_pipeline)
    monkeypatch.setitem(PIPELINES, "superpixel", fake_pipeline)
    image = np.full((*sparse.shape, 3), 128, np.uint8)
    api.complete_depth(image, sparse=sparse, K=K, return_std=False, trust_units=True)
    np.testing.assert_allclose(seen["sparse"], sparse, rtol=0, atol=0)
