"""Bad input through the Python API that gave a silent wrong answer, a traceback or a misleading message
(issue: every bad input gets a clear error): an upside-down sparse map, the K of another image size, a model
that is not a CRFDepth, half-precision tensors, torch.compile under inference_mode, NaN / inf images,
structured point arrays and centimetres told from millimetres."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from crfdepth.api import check_frame, complete_batch, complete_checked, complete_depth
from crfdepth.data.synthetic import make_scene
from crfdepth.errors import InputError
from crfdepth.inputs import points_to_sparse
from crfdepth.intrinsics import IntrinsicsWarning, check_intrinsics
from crfdepth.io.calibration import RigCalibration
from crfdepth.layer import CRFRefine, crf_refine
from crfdepth.model import CRFDepth
from crfdepth.plausibility import PlausibilityWarning, UpsideDownWarning, check_sparse_plausible

NYU = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nyu"
NYU_K = np.array([[518.86, 0, 325.58], [0, 519.47, 253.74], [0, 0, 1]])  # ../shared/data/nyu/README.md


@pytest.fixture(scope="module")
def scene():
    return make_scene(0, height=176, width=608, beams=16)


@pytest.fixture(scope="module")
def small():
    return make_scene(1, height=48, width=160, beams=16)


@pytest.fixture(scope="module")
def model():
    return CRFDepth(mode="pixel").eval()


def _no_plausibility_warning():
    context = warnings.catch_warnings()
    context.__enter__()
    warnings.simplefilter("error", PlausibilityWarning)
    return context


def _first_line(record) -> str:
    return str(record.message).splitlines()[0]


# --------------------------------------------------------------------------- 1. upside-down sparse map


def test_upside_down_sparse_map_is_warned_and_the_upright_one_is_not(scene):
    with warnings.catch_warnings():
        warnings.simplefilter("error", PlausibilityWarning)
        check_frame(scene.image, scene.sparse, scene.K)
    with pytest.warns(UpsideDownWarning) as record:
        check_frame(scene.image, scene.sparse[::-1].copy(), scene.K)
    assert _first_line(record[0]).startswith(
        "sparse: expected depth that decreases towards the bottom of the image (the ground nearest at the bottom), "
        "got a map that looks upside down: the depth increases downwards")
    assert "flip it (sparse[::-1]" in str(record[0].message)


def test_points_projected_upside_down_name_points_and_T_cam_lidar(scene):
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])  # a camera frame with y up (and x left): the image turned 180 degrees
    rig = RigCalibration(K=scene.K, T_cam_lidar=flip @ scene.T_cam_lidar, image_size=scene.image.shape[:2],
                         source="arguments")  # as complete_depth(K=..., T_cam_lidar=...) builds it
    with pytest.warns(UpsideDownWarning) as record:
        points_to_sparse(scene.points, rig, scene.image.shape[:2])
    assert _first_line(record[0]).startswith("points / T_cam_lidar: expected depth that decreases towards the bottom")
    upright = RigCalibration(K=scene.K, T_cam_lidar=scene.T_cam_lidar, image_size=scene.image.shape[:2])
    with warnings.catch_warnings():
        warnings.simplefilter("error", PlausibilityWarning)
        points_to_sparse(scene.points, upright, scene.image.shape[:2])


@pytest.mark.kitti
def test_real_kitti_frames_warn_nothing_and_flipped_they_warn(kitti_root):
    from crfdepth.io.kitti import read_depth_png, read_intrinsics, read_rgb

    root = kitti_root / "depth_selection" / "val_selection_cropped"
    paths = sorted((root / "velodyne_raw").glob("*.png"))
    assert paths
    for path in paths:
        stem = path.name.replace("velodyne_raw", "image")
        K = read_intrinsics(root / "intrinsics" / stem.replace(".png", ".txt"))
        image, sparse = read_rgb(root / "image" / stem), read_depth_png(path)
        with warnings.catch_warnings():
            warnings.simplefilter("error", PlausibilityWarning)
            check_frame(image, sparse, K)  # the crop's K (cx - 13, cy - 23) is no IntrinsicsWarning either
        with pytest.warns(UpsideDownWarning, match=r"^sparse: expected depth that decreases"):
            check_frame(image, sparse[::-1].copy(), K)


# --------------------------------------------------------------------------- 2. K of another image size


def test_K_of_a_smaller_image_on_a_2x_upscale_is_warned(scene):
    image = cv2.resize(scene.image, None, fx=2, fy=2, interpolation=cv2.INTER_LINEAR)
    sparse = np.zeros(image.shape[:2], np.float32)
    sparse[::2, ::2] = scene.sparse
    with pytest.warns(IntrinsicsWarning) as record:
        check_frame(image, sparse, scene.K)
    first = _first_line(record[0])
    assert first.startswith("K: expected the principal point near the centre of the 1216x352 (WxH) image, got "
                            f"(cx, cy) = ({scene.K[0, 2]:g}, {scene.K[1, 2]:g}), at (0.25, 0.21)")
    assert "K looks like the intrinsics of a 597x150 image" in first


@pytest.mark.parametrize("factor", [2, 0.5])
def test_K_of_another_size_through_complete_depth_is_warned(small, model, factor):
    h, w = small.image.shape[:2]
    size = (round(h * factor), round(w * factor))
    image = cv2.resize(small.image, size[::-1], interpolation=cv2.INTER_AREA)
    sparse = cv2.resize(small.sparse, size[::-1], interpolation=cv2.INTER_NEAREST)
    with pytest.warns(IntrinsicsWarning, match=rf"^K: expected the principal point near the centre of the "
                                               rf"{size[1]}x{size[0]} \(WxH\) image"):
        complete_depth(image, sparse=sparse, K=small.K, model=model, return_std=False)


def test_crops_and_real_intrinsics_are_not_warned():
    with warnings.catch_warnings():
        warnings.simplefilter("error", PlausibilityWarning)
        kitti = np.array([[721.5377, 0, 609.5593], [0, 721.5377, 172.854], [0, 0, 1]])
        check_intrinsics(kitti, "K", (375, 1242))
        crop = kitti - np.array([[0, 0, 13], [0, 0, 23], [0, 0, 0]])  # KITTI's depth-selection crop
        check_intrinsics(crop, "K", (352, 1216))
        top = kitti - np.array([[0, 0, 0], [0, 0, 100], [0, 0, 0]])  # the sky cropped off
        check_intrinsics(top, "K", (275, 1242))
        check_intrinsics(NYU_K, "K", (480, 640))
        check_intrinsics(NYU_K - np.array([[0, 0, 40], [0, 0, 44], [0, 0, 0]]), "K", (425, 560))  # NYU's crop
        check_intrinsics(kitti + np.array([[0, 0, 900], [0, 0, 0], [0, 0, 0]]), "K", (375, 1242), crop=True)


def test_principal_point_outside_the_image_is_warned():
    K = np.array([[500.0, 0, 700], [0, 500, 100], [0, 0, 1]])
    with pytest.warns(IntrinsicsWarning, match=r"^K: expected the principal point near the centre of the 640x480 "
                                               r"\(WxH\) image, got \(cx, cy\) = \(700, 100\), outside the image"):
        check_intrinsics(K, "K", (480, 640))


@pytest.mark.skipif(not NYU.is_dir(), reason=f"NYU sample data not found at {NYU}")
def test_nyu_frame_warns_nothing():
    from crfdepth.io.kitti import read_rgb

    rng = np.random.default_rng(0)
    for depth_file in sorted((NYU / "official_test" / "basement").glob("sync_depth_*.png")):
        depth = cv2.imread(str(depth_file), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000
        image = read_rgb(depth_file.with_name(depth_file.name.replace("sync_depth", "rgb").replace(".png", ".jpg")))
        sparse = np.zeros_like(depth)
        pick = rng.choice(np.flatnonzero(depth > 0), 500, replace=False)
        sparse.flat[pick] = depth.flat[pick]
        with warnings.catch_warnings():
            warnings.simplefilter("error", PlausibilityWarning)
            check_frame(image, sparse, NYU_K)


# --------------------------------------------------------------------------- 3. model that is not a CRFDepth

MODEL_MESSAGE = ("model: expected a crfdepth.CRFDepth (CRFDepth.from_pretrained(), crfdepth.load_model(), or None "
                 "for the default), got {}")


@pytest.mark.parametrize("bad", [CRFRefine(3), torch.nn.Linear(2, 2), "kitti"])
def test_model_that_is_not_a_crfdepth_is_refused_by_every_function(small, bad):
    image = torch.from_numpy(small.image).permute(2, 0, 1)[None]
    sparse = torch.from_numpy(small.sparse)[None, None]
    K = torch.from_numpy(small.K).float()
    calls = [lambda: complete_depth(small.image, sparse=small.sparse, K=small.K, model=bad),
             lambda: complete_batch(image, sparse, K, model=bad),
             lambda: complete_checked(bad, image, sparse, K[None], return_std=False)]
    for call in calls:
        with pytest.raises(InputError) as err:
            call()
        assert str(err.value).splitlines()[0] == MODEL_MESSAGE.format(type(bad).__name__)


# --------------------------------------------------------------------------- 4. half-precision tensors


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_half_precision_tensors_work_close_to_float32(small, model, dtype):
    image = torch.from_numpy(small.image).permute(2, 0, 1)
    sparse, K = torch.from_numpy(small.sparse), torch.from_numpy(small.K)
    reference, _ = complete_depth(image, sparse=sparse, K=K, model=model, return_std=False)
    for kwargs in ({"image": image.to(dtype)}, {"sparse": sparse.to(dtype)}, {"K": K.to(dtype)}):
        given = {"image": image, "sparse": sparse, "K": K, **kwargs}
        depth, _ = complete_depth(given.pop("image"), **given, model=model, return_std=False)
        assert depth.dtype == torch.float32 and depth.shape == reference.shape
        # half precision rounds the inputs (bfloat16: 8 bits, depth to 0.4 %): the depth moves about as much
        assert float((depth - reference).abs().median()) < 0.01 * float(reference.median())
    with torch.no_grad():
        out = model(image[None].to(dtype), sparse[None, None], K.float())
        exact = model(image[None], sparse[None, None], K.float())
    assert float((out.depth - exact.depth).abs().median()) < 0.01 * float(exact.depth.median())


# --------------------------------------------------------------------------- 5. torch.compile + inference_mode


@pytest.mark.parametrize("mode", [torch.inference_mode, torch.no_grad])
def test_compiled_model_runs_under_inference_mode_and_no_grad(small, mode):
    """Dynamo failed inside the CRF with "Guard failed ... This is a bug" (an AssertionError); the CRF now runs
    eagerly inside the compiled forward and gives the eager depth."""
    model = CRFDepth(mode="pixel").eval()
    image = torch.from_numpy(small.image).permute(2, 0, 1)[None]
    sparse, K = torch.from_numpy(small.sparse)[None, None], torch.from_numpy(small.K).float()
    with torch.no_grad():
        eager = model(image, sparse, K).depth
    torch._dynamo.reset()
    with mode():
        depth = torch.compile(model)(image, sparse, K).depth
    torch.testing.assert_close(depth, eager, rtol=1e-5, atol=1e-5)
    with mode(), pytest.raises(InputError, match=r"^image: expected finite RGB values in \[0, 1\], got NaN at 1 "
                                                 r"pixel\(s\)$"):
        broken = image.clone()
        broken[0, 1, 3, 4] = float("nan")
        torch.compile(model)(broken, sparse, K)


# --------------------------------------------------------------------------- 6. NaN / inf image


@pytest.mark.parametrize("value, word", [(float("nan"), "NaN"), (float("inf"), "inf")])
def test_non_finite_image_is_told_so(small, model, value, word):
    rgb = small.image.copy()
    rgb[3, 4, 1] = value
    rgb[5, 6, :] = value
    with pytest.raises(InputError) as err:
        complete_depth(rgb, sparse=small.sparse, K=small.K, model=model)
    assert str(err.value).splitlines()[0] == f"image: expected float RGB in [0, 1] (finite values), got {word} at 2 " \
                                             f"pixel(s)"
    tensor = torch.from_numpy(rgb).permute(2, 0, 1)
    with pytest.raises(InputError, match=rf"^image: expected float RGB in \[0, 1\] \(finite values\), got {word} at "
                                         rf"2 pixel\(s\)$"):
        complete_depth(tensor, sparse=small.sparse, K=small.K, model=model)
    with pytest.raises(InputError) as err:
        model(tensor[None], torch.from_numpy(small.sparse)[None, None], torch.from_numpy(small.K).float())
    assert str(err.value).splitlines()[0] == f"image: expected finite RGB values in [0, 1], got {word} at 2 pixel(s)"


def test_non_finite_sparse_is_counted(small, model):
    sparse = small.sparse.copy()
    sparse[0, :3] = np.nan
    with pytest.raises(InputError, match=r"^sparse: expected finite depth >= 0 metres \(0 = no LiDAR point\), got "
                                         r"NaN at 3 pixel\(s\)$"):
        complete_depth(small.image, sparse=sparse, K=small.K, model=model)
    image = torch.from_numpy(small.image).permute(2, 0, 1)[None]
    with pytest.raises(InputError, match=r"^sparse: expected finite depth >= 0 in metres \(0 = no LiDAR\), got "
                                         r"NaN at 3 pixel\(s\)$"):
        model(image, torch.from_numpy(sparse)[None, None], torch.from_numpy(small.K).float())


# --------------------------------------------------------------------------- 7. structured point arrays


def _structured(points: np.ndarray, names=("x", "y", "z", "intensity")) -> np.ndarray:
    table = np.zeros(len(points), np.dtype([(n, np.float32) for n in names]))
    for i, n in enumerate(names):
        table[n] = points[:, i]
    return table


def test_structured_and_record_point_arrays_are_read(small, model):
    plain, _ = complete_depth(small.image, points=small.points, K=small.K, T_cam_lidar=small.T_cam_lidar,
                              model=model, return_std=False)
    table = _structured(small.points.astype(np.float32))
    for points in (table, table.view(np.recarray), table.reshape(-1, 1)):
        depth, _ = complete_depth(small.image, points=points, K=small.K, T_cam_lidar=small.T_cam_lidar, model=model,
                                  return_std=False)
        np.testing.assert_allclose(depth, plain, rtol=1e-4, atol=1e-4)


def test_structured_points_without_xyz_say_how_to_convert(small, model):
    table = _structured(small.points, names=("px", "py", "pz", "intensity"))
    with pytest.raises(InputError) as err:
        complete_depth(small.image, points=table, K=small.K, T_cam_lidar=small.T_cam_lidar, model=model)
    assert str(err.value).splitlines()[0] == (
        "points: expected a structured array with fields x, y, z (metres) or an (N, 3) array, got fields px, py, pz, "
        "intensity (no x, y, z); build the (N, 3) array yourself, e.g. np.stack([a['x'], a['y'], a['z']], -1)")


# --------------------------------------------------------------------------- 8. centimetres are not millimetres


@pytest.mark.parametrize("factor, advice", [(100, "centimetres: divide them by 100"),
                                            (1000, "millimetres: divide them by 1000")])
def test_points_in_centimetres_and_millimetres_get_their_own_advice(scene, factor, advice):
    rig = RigCalibration(K=scene.K, T_cam_lidar=scene.T_cam_lidar, image_size=scene.image.shape[:2])
    with pytest.raises(InputError) as err:
        points_to_sparse(scene.points * factor, rig, scene.image.shape[:2])
    first = str(err.value).splitlines()[0]
    assert first.startswith("points: expected coordinates in metres (a median depth of at most 300 m), got a median "
                            "projected depth of ")
    assert first.split("; ")[1] == f"the point coordinates look like {advice}"


@pytest.mark.parametrize("factor, advice", [(100, "centimetres: divide by 100"), (1000, "millimetres: divide by 1000")])
def test_sparse_maps_in_centimetres_and_millimetres_get_their_own_advice(scene, factor, advice):
    for K in (scene.K, None):  # with the ground below the camera, and from the median alone
        with pytest.raises(InputError) as err:
            check_sparse_plausible("sparse", scene.sparse * factor, K)
        assert str(err.value).splitlines()[0].split("; ")[1] == f"that looks like {advice}"


@pytest.mark.parametrize("name", ["return_std", "trust_transform", "trust_units"])
def test_a_flag_that_is_not_a_bool_is_refused_by_name(name):
    """A string is truthy whatever it says: return_std="no" must not run the std."""
    scene = make_scene(seed=0)
    with pytest.raises(InputError) as info:
        complete_depth(scene.image, sparse=scene.sparse, K=scene.K, **{name: "no"})
    assert str(info.value) == f"{name}: expected True or False, got 'no'"


def test_forward_and_the_layer_refuse_a_return_std_that_is_not_a_bool():
    tensors = make_scene(seed=0).to_tensors()
    with pytest.raises(InputError, match=r"^return_std: expected True or False, got 1$"):
        CRFDepth()(tensors["image"][None], tensors["sparse"][None], tensors["K"][None], return_std=1)
    depth = torch.ones(1, 1, 4, 4)
    with pytest.raises(InputError, match=r"^return_std: expected True or False, got 'yes'$"):
        crf_refine(depth, depth, torch.zeros(1, 3, 4, 4), torch.zeros(2, 3), return_std="yes")
