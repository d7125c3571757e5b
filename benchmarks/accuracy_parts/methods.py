"""The methods and how each is run on one frame; the learned weights come from :mod:`.fits`.

Methods (every CRF is :class:`crfdepth.model.CRFDepth`, float32, batch size 1):

- ``nn``: nearest-LiDAR fill (:func:`crfdepth.fill.nearest.nearest_fill`);
- ``ipbasic``: IP-Basic (Ku et al. 2018), fast configuration, as written here in torch
  (:func:`crfdepth.fill.ip_basic.ip_basic_fill`); the classical baseline to beat;
- ``inpaint``: OpenCV ``cv2.inpaint`` (Telea, radius 5) of the sparse map as float32
  metres (OpenCV 5 takes 1-channel float32), clipped to the input's depth range (Telea
  overshoots below 0 near the image border otherwise);
- ``paper``: ``CRFDepth()`` (superpixel 5500, all potentials, pixel refinement) with the
  hand-set weights (``CRFDepth.from_pretrained("paper")``);
- ``hand-set``: the structure of the shipped weights (the recipe's ``model.crf``
  section) with the constructor's hand-set weights: what learning is measured against;
- ``learned``: that structure with weights learned by the recipe of the shipped weights
  (``configs/kitti_weights.yaml``: the Lightning trainer, its loss, optimiser,
  augmentation, hold-outs, epochs and seed), always on frames **outside** the
  evaluated set. Protocol a: the shipped weights themselves (``crfdepth/weights/kitti.json``,
  the package default; trained on drive 0060 and the object frames, never on drive 0001).
  Protocol s: the shipped weights (never trained on synthetic scenes).
  Protocols b and c: 2-fold by source, since the shipped weights saw those frames: the
  raw-drive frames get weights fitted on the object frames, the object frames weights
  fitted on the raw drives. The NLL term is off in these fits (it moves only the std
  scale, which changes neither the depth nor the AUSE). Which fit served which frames is
  in the output (``fit``);
- ``default``: ``CRFDepth.from_pretrained()``, what the API and the CLI use: the shipped weights, and for
  frames with few returns their sparse regime (docs/design.md section 17); unlike ``learned`` never re-fitted;
- ``shipped``: ``CRFDepth.from_pretrained(adaptive=False)``, the shipped weights on every frame (the
  default before the sparse regime), never re-fitted;
- ``coarse``: the scattered sparse regime alone, ``CRFDepth(mode="pixel", coarse=6, near_inverse=10,
  coarse_shifts=2)`` (hand-set weights, a coarse solve on 6-pixel blocks first, twice as tall on a line scan,
  near blocks from inverse depth, a second grid shifted by half a block); ``coarse+1grid``: the same with one
  grid; ``coarse+depth``: one grid, the depth unknown alone;
- ``coarse+log``, ``coarse+inv``: that regime with the log-depth or the inverse-depth unknown (section 17: the
  unknown trades RMSE for REL);
- ``pixel``: ``CRFDepth(mode="pixel")``;
- ``sp-c``, ``sp-cn``, ``sp-cnd``: the paper's Table 1 ablation (colour; + normal; +
  3D distance), superpixel 5500, piecewise-constant painting (``refine=False``);
  ``sp-c+r``, ``sp-cn+r``: the same with the pixel refinement (``sp-cnd+r`` is ``paper``);
- ``sp1200``, ``sp2400``: the paper's Table 2 segment counts, all potentials, no
  refinement (5500 is ``sp-cnd``);
- ``inv``, ``inv+gate``, ``pixel+gate``, ``pixel+inv+gate``, ``pixel+inv+gate+ipb``,
  ``pixel+inv+gate+irls``, ``pixel+log+gate``: the extensions of docs/design.md section 3b
  with hand-set weights (``variable="inverse"`` or ``"log"``, ``gate=True``,
  ``mode="pixel"``, ``prior="ip_basic"``, ``irls=1``).

The ablations and segment counts use the hand-set weights, as ``paper`` does. With
``--learn-ablations``, protocol a also gets ``sp-c/learned`` .. ``sp-cn+r/learned``: each
ablation with weights learned for its own configuration by the shipped recipe on the
shipped weights' training frames (drive 0060 and the object frames, never drive 0001), as
the paper trains each row of its Table 1 (5 more fits, about 5 minutes each on 2 cores).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from crfdepth.fill.ip_basic import ip_basic_fill
from crfdepth.fill.nearest import nearest_fill
from crfdepth.model import CRFDepth

RECIPE = Path(__file__).resolve().parents[2] / "configs" / "kitti_weights.yaml"
CRF_METHODS = {
    "paper": {},
    "learned": {},
    "hand-set": {},  # the recipe's structure (recipe_crf()), the constructor's weights
    "default": {},  # CRFDepth.from_pretrained(): the shipped weights and their sparse regime
    "shipped": {},  # CRFDepth.from_pretrained(adaptive=False): the shipped weights alone, every frame
    # the scattered regime alone: hand-set, pixel grid, coarse solve (near blocks from inverse depth, two grids)
    "coarse": {"mode": "pixel", "coarse": 6, "near_inverse": 10.0, "coarse_shifts": 2},
    # that regime with one coarse grid (section 17: cycle spinning)
    "coarse+1grid": {"mode": "pixel", "coarse": 6, "near_inverse": 10.0},
    # the scattered regime with the depth unknown alone, and with the other unknowns (section 17: the RMSE / REL
    # trade of the unknown)
    "coarse+depth": {"mode": "pixel", "coarse": 6},
    "coarse+log": {"mode": "pixel", "coarse": 6, "variable": "log"},
    "coarse+inv": {"mode": "pixel", "coarse": 6, "variable": "inverse"},
    "pixel": {"mode": "pixel"},
    "sp-c": {"potentials": ("colour",), "refine": False},
    "sp-cn": {"potentials": ("colour", "normal"), "refine": False},
    "sp-cnd": {"refine": False},
    "sp-c+r": {"potentials": ("colour",)},
    "sp-cn+r": {"potentials": ("colour", "normal")},
    "sp1200": {"superpixels": 1200, "refine": False},
    "sp2400": {"superpixels": 2400, "refine": False},
    # docs/design.md section 3b, hand-set weights: 1/z unknown, occlusion gate, on both graphs
    "inv": {"variable": "inverse"},
    "inv+gate": {"variable": "inverse", "gate": True},
    "pixel+gate": {"mode": "pixel", "gate": True},
    "pixel+inv+gate": {"mode": "pixel", "variable": "inverse", "gate": True},
    "pixel+inv+gate+ipb": {"mode": "pixel", "variable": "inverse", "gate": True, "prior": "ip_basic"},
    "pixel+inv+gate+irls": {"mode": "pixel", "variable": "inverse", "gate": True, "irls": 1},
    "pixel+log+gate": {"mode": "pixel", "variable": "log", "gate": True},
}
METHODS = ("nn", "ipbasic", "inpaint", *CRF_METHODS)
PRETRAINED = {"default": {}, "shipped": {"adaptive": False}}  # methods built by CRFDepth.from_pretrained(**...)
WITH_STD = ("paper", "hand-set", "learned")


def recipe() -> dict:
    import yaml

    return yaml.safe_load(RECIPE.read_text())


def recipe_crf() -> dict:
    """The model structure of the shipped recipe (its ``model.crf`` section)."""
    return dict(recipe()["model"].get("crf") or {})


def method_config(method: str) -> dict:
    return recipe_crf() if method == "hand-set" else dict(CRF_METHODS[method])


# The Table 1 ablations with weights learned for each configuration (protocol a only:
# ``--learn-ablations``), as the paper does.
LEARNED_ABLATIONS = {f"{m}/learned": CRF_METHODS[m] for m in ("sp-c", "sp-cn", "sp-cnd", "sp-c+r", "sp-cn+r")}


def inpaint(sparse: torch.Tensor) -> torch.Tensor:
    """cv2.inpaint (Telea, radius 5) of a (1, 1, H, W) sparse map in metres, float32."""
    import cv2

    d = sparse[0, 0].detach().cpu().numpy().astype(np.float32)
    valid = d > 0
    out = cv2.inpaint(d, (~valid).astype(np.uint8), 5, cv2.INPAINT_TELEA)
    out = np.clip(out, d[valid].min(), d[valid].max())
    return torch.from_numpy(out)[None, None].to(sparse)


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def predict(method: str, model: CRFDepth | None, image, sparse, K, device: str):
    """(depth (1, 1, H, W), std or None, count map or None, seconds); ``std`` is the model's own
    (the predictive std unless it was built with ``uncertainty="posterior"``)."""
    sync(device)
    t = time.perf_counter()
    std = count = None
    with torch.no_grad():
        if method == "nn":
            depth = nearest_fill(sparse)
        elif method == "ipbasic":
            depth = ip_basic_fill(sparse)
        elif method == "inpaint":
            depth = inpaint(sparse)
        else:
            out = model(image, sparse, K, return_std=method in WITH_STD)
            depth, std, count = out.depth, out.std, out.count_uncertainty
    sync(device)
    seconds = time.perf_counter() - t
    if model is not None and method in WITH_STD:
        seconds -= out.timings.get("uncertainty", 0.0)
    return depth.clamp_min(1e-3), std, count, seconds

