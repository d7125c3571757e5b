"""Tests of the torch SLIC (crfdepth.superpixels.slic, .connectivity) against scikit-image's, on synthetic and real frames."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage
from skimage.measure import label as connected_components
from skimage.segmentation import felzenszwalb, slic
from skimage.util import regular_grid

from crfdepth.data.synthetic import make_scene
from crfdepth.errors import InputError
from crfdepth.superpixels.connectivity import connected_segments
from crfdepth.superpixels.segments import _CPU_BACKEND, slic_segments
from crfdepth.superpixels.slic import _gaussian_blur, _kmeans, _regular_grid, slic_torch

SLIC = dict(compactness=20.0, sigma=1.0, max_num_iter=5, convert2lab=True)  # slic_segments' defaults


def skimage_slic(image: torch.Tensor, n_segments: int, *, enforce_connectivity: bool = True, **kw) -> np.ndarray:
    """scikit-image's SLIC of a (3, H, W) tensor with the parameters of slic_segments."""
    options = {**SLIC, **kw}
    rgb = image.permute(1, 2, 0).to(torch.float32).contiguous().numpy()
    return slic(rgb, n_segments=n_segments, enforce_connectivity=enforce_connectivity, start_label=0,
                channel_axis=-1, **options)


def kmeans_labels(image: torch.Tensor, n_segments: int, max_num_iter: int) -> np.ndarray:
    """The torch k-means labels before the connectivity pass, as scikit-image's seed indices."""
    from crfdepth.superpixels.slic import _colour_features

    h, w = image.shape[-2:]
    grid = _regular_grid(h, w, n_segments)
    colour = _colour_features(image[None].to(torch.float32), SLIC["compactness"], SLIC["sigma"], True)
    index = _kmeans(colour, grid, max_num_iter)[0].numpy()
    (_, sy), (x0, sx) = grid
    gx = -(-w // sx) + 2  # width of the padded seed grid (one block of padding each side)
    nx = len(range(x0, w, sx))
    return (index // gx - 1) * nx + (index % gx - 1)


def is_consecutive(labels: np.ndarray) -> bool:
    return bool(np.array_equal(np.unique(labels), np.arange(labels.max() + 1)))


def n_components(labels: np.ndarray) -> int:
    """Number of 4-connected regions of equal label."""
    return int(connected_components(labels + 1, connectivity=1, background=0).max())


def boundary(labels: np.ndarray) -> np.ndarray:
    """Pixels with a horizontal or vertical neighbour of another label (both sides)."""
    edge = np.zeros(labels.shape, dtype=bool)
    step = labels[:, 1:] != labels[:, :-1]
    edge[:, 1:] |= step
    edge[:, :-1] |= step
    step = labels[1:] != labels[:-1]
    edge[1:] |= step
    edge[:-1] |= step
    return edge


def boundary_recall(labels: np.ndarray, reference: np.ndarray, tolerance: int = 2) -> float:
    """Fraction of the reference boundary pixels within ``tolerance`` pixels (Chebyshev) of a segment boundary."""
    near = ndimage.binary_dilation(boundary(labels), np.ones((2 * tolerance + 1,) * 2, dtype=bool))
    return float(near[reference].mean())


def undersegmentation_error(labels: np.ndarray, reference: np.ndarray) -> float:
    """Neubert & Protzel (2012): ``sum_S sum_G min(|S & G|, |S - G|) / N`` over overlapping pairs."""
    n_ref = int(reference.max()) + 1
    joint = np.bincount((labels.astype(np.int64) * n_ref + reference).ravel(),
                        minlength=(int(labels.max()) + 1) * n_ref).reshape(-1, n_ref)
    size = joint.sum(axis=1, keepdims=True)
    return float(np.minimum(joint, size - joint)[joint > 0].sum() / labels.size)


def depth_edges(depth: np.ndarray, jump: float = 0.05) -> np.ndarray:
    """Both pixels of each 4-neighbour pair with ground truth whose depths differ by > ``jump`` relative."""
    edge = np.zeros(depth.shape, dtype=bool)
    for a, b, sa, sb in ((depth[:, :-1], depth[:, 1:], np.s_[:, :-1], np.s_[:, 1:]),
                         (depth[:-1], depth[1:], np.s_[:-1], np.s_[1:])):
        step = (a > 0) & (b > 0) & (np.abs(a - b) > jump * np.minimum(a, b))
        edge[sa] |= step
        edge[sb] |= step
    return edge


def oracle_rmse(labels: np.ndarray, depth: np.ndarray) -> float:
    """RMSE (m) of each segment painted with its mean ground truth (the measure of slic_segments' docstring)."""
    valid = depth > 0
    n = int(labels.max()) + 1
    mean = np.bincount(labels[valid], depth[valid], n) / np.maximum(np.bincount(labels[valid], minlength=n), 1)
    return float(np.sqrt(np.mean((mean[labels[valid]] - depth[valid]) ** 2)))


@pytest.fixture(scope="module")
def scene_image() -> torch.Tensor:
    """(3, 352, 1216) synthetic street frame, float32 RGB in [0, 1]."""
    return torch.from_numpy(make_scene(0).image).permute(2, 0, 1).contiguous()


# --------------------------------------------------------------------------- building blocks


def test_seed_grid_is_scikit_images():
    rng = np.random.default_rng(0)
    shapes = [(352, 1216, 5500), (1, 1, 1), (1, 7, 3), (5, 7, 100), (3, 200, 30), (200, 3, 30), (64, 64, 10)]
    shapes += [tuple(int(v) for v in rng.integers(1, 400, 2)) + (int(rng.integers(1, 3000)),) for _ in range(300)]
    for h, w, n in shapes:
        slices = regular_grid((1, h, w), n)
        expected = tuple((s.start or 0, s.step or 1) for s in slices[1:])
        assert _regular_grid(h, w, n) == expected, (h, w, n)


@pytest.mark.parametrize(("size", "sigma"), [((40, 57), 1.0), ((40, 57), 0.6), ((3, 5), 2.0), ((1, 9), 1.0)])
def test_gaussian_blur_is_scipys_reflect_filter(size, sigma):
    x = torch.rand(2, 3, *size, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    expected = ndimage.gaussian_filter(x.numpy(), sigma=(0, 0, sigma, sigma), mode="reflect", truncate=4.0)
    np.testing.assert_allclose(_gaussian_blur(x, sigma).numpy(), expected, rtol=0, atol=1e-12)


def test_connected_components_match_scipy_label():
    gen = torch.Generator().manual_seed(2)
    labels = torch.randint(0, 4, (3, 31, 45), generator=gen)
    segments = connected_segments(labels, min_size=0).numpy()
    for frame, seg in zip(labels.numpy(), segments):
        assert is_consecutive(seg)
        ref = connected_components(frame + 1, connectivity=1, background=0)
        assert seg.max() + 1 == ref.max()
        # Same partition: each segment is exactly one scipy component and vice versa.
        pairs = np.unique(np.stack([seg.ravel(), ref.ravel()]), axis=1)
        assert pairs.shape[1] == ref.max()


def test_small_fragment_joins_its_largest_neighbour():
    # Row 2 holds a 1-pixel fragment of label 7 between a 12-pixel region (label 1)
    # and a 3-pixel region (label 2); a lone 7 in the corner touches only label 1.
    labels = torch.tensor([[1, 1, 1, 1, 2],
                           [1, 1, 1, 1, 2],
                           [1, 1, 1, 7, 2],
                           [7, 1, 1, 1, 1]])
    segments = connected_segments(labels[None], min_size=2)[0]
    assert segments.tolist() == [[0, 0, 0, 0, 1],
                                 [0, 0, 0, 0, 1],
                                 [0, 0, 0, 0, 1],
                                 [0, 0, 0, 0, 0]]


# --------------------------------------------------------------------------- synthetic frame


def test_kmeans_agrees_with_scikit_image_on_the_synthetic_frame(scene_image):
    # Before the connectivity pass the only difference is the candidate set (3x3 seed
    # blocks here, every centre within two grid steps in scikit-image).
    for iterations in (1, 5):
        ref = skimage_slic(scene_image, 5500, enforce_connectivity=False, max_num_iter=iterations)
        agree = float(np.mean(kmeans_labels(scene_image, 5500, iterations) == ref))
        assert agree >= (1.0 if iterations == 1 else 0.999), (iterations, agree)


def test_synthetic_frame_segments_are_consecutive_connected_and_count_like_scikit_image(scene_image):
    labels = slic_torch(scene_image, 5500)
    assert labels.shape == (352, 1216) and labels.dtype == torch.int64
    seg = labels.numpy()
    s = int(seg.max()) + 1
    assert is_consecutive(seg)
    assert n_components(seg) == s
    s_ref = int(skimage_slic(scene_image, 5500).max()) + 1
    assert abs(s - s_ref) <= 0.02 * s_ref, (s, s_ref)
    assert 0.85 * 5500 <= s <= 5500


def test_batch_equals_single_frames_for_float32_and_float64():
    gen = torch.Generator().manual_seed(3)
    coarse = torch.rand(3, 3, 6, 9, generator=gen, dtype=torch.float64)
    images = torch.nn.functional.interpolate(coarse, size=(60, 90), mode="bilinear", align_corners=False)
    images[2] = 0.3 + 0.4 * images[2]  # a low-contrast frame: stretched by its own min/max
    before = images.clone()
    batched = slic_torch(images, 80)
    assert batched.shape == (3, 60, 90) and batched.dtype == torch.int64
    assert torch.equal(images, before)  # input untouched
    for k in range(3):
        single = slic_torch(images[k], 80)
        assert torch.equal(single, batched[k])
        assert torch.equal(slic_torch(images[k].to(torch.float32), 80), single)
        seg = single.numpy()
        assert is_consecutive(seg) and n_components(seg) == seg.max() + 1
        assert 0.5 * 80 <= seg.max() + 1 <= 1.5 * 80


@pytest.mark.parametrize(
    ("size", "n_segments"), [((1, 1), 1), ((1, 7), 3), ((5, 7), 100), ((20, 30), 1), ((3, 200), 30)]
)
def test_tiny_images_and_extreme_counts_give_valid_segments(size, n_segments):
    image = torch.rand(3, *size, generator=torch.Generator().manual_seed(4))
    seg = slic_torch(image, n_segments).numpy()
    assert seg.shape == size and is_consecutive(seg) and n_components(seg) == seg.max() + 1
    assert seg.max() + 1 == skimage_slic(image, n_segments).max() + 1


def test_constant_image_gives_grid_segments_like_scikit_image():
    image = torch.full((3, 20, 30), 0.5)
    seg = slic_torch(image, 6).numpy()
    # Seeds 10 px apart at rows 5, 15 and columns 5, 15, 25; a pixel halfway between two
    # seeds (row or column 10, column 20 after the first update) goes to the first one.
    rows = np.where(np.arange(20) <= 10, 0, 1)
    cols = np.searchsorted([10, 20], np.arange(30), side="left")
    assert np.array_equal(seg, rows[:, None] * 3 + cols[None, :])
    assert np.array_equal(seg, skimage_slic(image, 6))


def test_rgb_mode_runs_without_lab():
    image = torch.rand(3, 40, 60, generator=torch.Generator().manual_seed(5))
    seg = slic_torch(image, 24, compactness=0.2, sigma=0.0, convert2lab=False).numpy()
    assert is_consecutive(seg) and n_components(seg) == seg.max() + 1


# --------------------------------------------------------------------------- slic_segments backends


def test_slic_segments_backends(scene_image):
    crop = scene_image[:, :120, :300]
    torch_labels = slic_segments(crop, 300, backend="torch")
    assert torch.equal(torch_labels, slic_torch(crop, 300))
    assert torch.equal(slic_segments(crop.permute(1, 2, 0).numpy(), 300, backend="torch"), torch_labels)
    sk = slic_segments(crop, 300, backend="skimage").numpy()
    ref = skimage_slic(crop, 300)
    _, ref_consecutive = np.unique(ref, return_inverse=True)
    assert np.array_equal(sk, ref_consecutive.reshape(ref.shape))
    expected = torch_labels if _CPU_BACKEND == "torch" else torch.from_numpy(sk)
    assert torch.equal(slic_segments(crop, 300), expected)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_gpu_result_stays_on_the_device_and_matches_the_cpu(scene_image):
    cpu = slic_torch(scene_image, 5500).numpy()
    gpu = slic_torch(scene_image.cuda(), 5500)
    assert gpu.device.type == "cuda" and gpu.dtype == torch.int64
    assert slic_segments(scene_image.cuda(), 5500).device.type == "cuda"
    seg = gpu.cpu().numpy()
    assert is_consecutive(seg) and n_components(seg) == seg.max() + 1
    assert abs(int(seg.max()) - int(cpu.max())) <= 0.005 * cpu.max()
    assert np.mean(boundary(seg) == boundary(cpu)) >= 0.995


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        (dict(image=torch.rand(4, 8, 8)), "image"),
        (dict(image=torch.rand(8, 8)), "image"),
        (dict(image=torch.rand(1, 1, 3, 8, 8)), "image"),
        (dict(image=torch.ones(3, 8, 8) * 1.5), "image"),
        (dict(image=-torch.ones(3, 8, 8)), "image"),
        (dict(image=torch.full((3, 8, 8), float("nan"))), "image"),
        (dict(image=torch.ones(3, 8, 8, dtype=torch.uint8)), "image"),
        (dict(image=np.ones((3, 8, 8))), "image"),
        (dict(n_segments=0), "n_segments"),
        (dict(n_segments=2.5), "n_segments"),
        (dict(n_segments=True), "n_segments"),
        (dict(compactness=0.0), "compactness"),
        (dict(sigma=-1.0), "sigma"),
        (dict(max_num_iter=0), "max_num_iter"),
        (dict(convert2lab="yes"), "convert2lab"),
    ],
)
def test_bad_input_names_the_argument(kwargs, name):
    args = dict(image=torch.rand(3, 8, 8), n_segments=4)
    args.update(kwargs)
    image, n = args.pop("image"), args.pop("n_segments")
    with pytest.raises(InputError, match=rf"^{name}: expected"):
        slic_torch(image, n, **args)


@pytest.mark.parametrize("backend", ["cuda", "Torch", None, 1])
def test_bad_backend_names_the_argument(backend):
    with pytest.raises(InputError, match=r"^backend: expected one of 'auto', 'torch', 'skimage', got"):
        slic_segments(torch.rand(3, 8, 8), 4, backend=backend)


def test_slic_segments_torch_backend_checks_image_and_count():
    with pytest.raises(InputError, match=r"^image: expected RGB values in \[0, 1\]"):
        slic_segments(torch.full((3, 8, 8), 2.0), 4, backend="torch")
    with pytest.raises(InputError, match=r"^n_segments: expected an integer >= 1"):
        slic_segments(torch.rand(3, 8, 8), 0, backend="torch")


# --------------------------------------------------------------------------- real KITTI frames


@pytest.fixture(scope="module")
def real_frames(kitti_root):
    """Both val_selection_cropped frames: image, ground truth and both segmentations."""
    from crfdepth.data.kitti import KittiValSelection

    data = KittiValSelection(kitti_root / "depth_selection" / "val_selection_cropped")
    samples = [data[k] for k in range(len(data))]
    images = torch.stack([s.image for s in samples])
    ours = slic_torch(images, 5500).numpy()  # one batched call
    frames = []
    for k, sample in enumerate(samples):
        rgb = sample.image.permute(1, 2, 0).numpy()
        frames.append(dict(
            image=sample.image,
            depth=sample.target[0].numpy(),
            torch=ours[k],
            skimage=skimage_slic(sample.image, 5500),
            # Independent reference segmentation (about 300 regions): Felzenszwalb's graph cut.
            reference=felzenszwalb(rgb, scale=200, sigma=0.8, min_size=100),
        ))
    return frames


@pytest.mark.kitti
def test_real_frames_segments_are_consecutive_connected_and_count_like_scikit_image(real_frames):
    # Measured: 5200 vs 5199 and 5208 vs 5208 segments.
    for frame in real_frames:
        seg = frame["torch"]
        s, s_ref = int(seg.max()) + 1, int(frame["skimage"].max()) + 1
        assert is_consecutive(seg) and n_components(seg) == s
        assert abs(s - s_ref) <= 0.02 * s_ref, (s, s_ref)


@pytest.mark.kitti
def test_real_frames_boundary_recall_of_depth_edges_matches_scikit_image(real_frames):
    # Reference boundaries: ground-truth depth jumps of more than 5% between 4-neighbours
    # (about 2300 pixels per frame). Depth edges are what the superpixels must follow for
    # depth completion, and they do not come from the colours SLIC clusters. Measured
    # recall within 2 px: 0.9356 vs 0.9364 and 0.9174 vs 0.9183 (torch vs scikit-image).
    for frame in real_frames:
        edges = depth_edges(frame["depth"])
        assert edges.sum() > 1000
        ours, ref = boundary_recall(frame["torch"], edges), boundary_recall(frame["skimage"], edges)
        assert ours >= 0.85 and abs(ours - ref) <= 0.01, (ours, ref)


@pytest.mark.kitti
def test_real_frames_undersegmentation_error_matches_scikit_image(real_frames):
    # Both against the same Felzenszwalb segmentation. Measured: 0.2123 vs 0.2121 and
    # 0.2058 vs 0.2052 (torch vs scikit-image).
    for frame in real_frames:
        ours = undersegmentation_error(frame["torch"], frame["reference"])
        ref = undersegmentation_error(frame["skimage"], frame["reference"])
        assert abs(ours - ref) <= 0.005, (ours, ref)


@pytest.mark.kitti
def test_real_frames_oracle_depth_rmse_matches_scikit_image(real_frames):
    # Each segment painted with its mean ground truth. Measured: 1.139 vs 1.146 m and
    # 1.111 vs 1.111 m (torch vs scikit-image).
    for frame in real_frames:
        ours, ref = oracle_rmse(frame["torch"], frame["depth"]), oracle_rmse(frame["skimage"], frame["depth"])
        assert abs(ours - ref) <= 0.03 * ref, (ours, ref)


@pytest.mark.kitti
def test_real_frames_kmeans_agrees_with_scikit_image(real_frames):
    # Measured: 99.989% and 99.964% of the pixels get the same centre after 5 iterations.
    for frame in real_frames:
        ref = skimage_slic(frame["image"], 5500, enforce_connectivity=False)
        assert float(np.mean(kmeans_labels(frame["image"], 5500, 5) == ref)) >= 0.999
