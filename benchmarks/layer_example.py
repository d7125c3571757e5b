"""The CRF as a layer: a tiny CNN with :class:`crfdepth.layer.CRFRefine` on top (issue 5).

A small CNN (about 10k parameters) reads the image, the sparse LiDAR, its validity mask
and the nearest-LiDAR fill, and predicts a depth (the fill plus a residual), a per-pixel
confidence and guidance features. Two models with the same architecture, the same
initial weights (same seed), the same data and the same number of Adam steps are trained:

- ``cnn``: L1 loss on the CNN's own depth;
- ``cnn+crf``: L1 loss on the output of ``CRFRefine(depth, confidence, features, sparse)``
  only, so the CNN learns through the layer.

Data: built-in synthetic street scenes (:func:`crfdepth.data.synthetic.make_scene`)
rendered at 88x304 with a 16-beam LiDAR (``--beams``); training seeds ``0 ..
train-1``, held-out seeds from 1000. Loss and metrics on the scene's KITTI-like target
pixels. Reported: (a) the gradient norm that reaches the CNN's first convolution through
the layer (loss on the CRF output only), (b) held-out RMSE / MAE of both models.

Run: ``OMP_NUM_THREADS=1 python benchmarks/layer_example.py [--steps 150]``; prints a table
and one JSON line. ``tests/test_layer.py`` runs a short version and asserts (a) and (b).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from crfdepth.data.synthetic import make_scene
from crfdepth.fill.nearest import nearest_fill
from crfdepth.layer import CRFRefine
from crfdepth.metrics import average_metrics, depth_metrics

if str(Path(__file__).resolve().parent) not in sys.path:  # a load by the file's path (the tests) has not
    sys.path.append(str(Path(__file__).resolve().parent))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)


def make_batch(seeds, height: int = 88, width: int = 304, beams: int = 16) -> dict[str, torch.Tensor]:
    """Synthetic scenes as one batch: image (B,3,H,W), sparse/fill/target (B,1,H,W) metres."""
    scenes = [make_scene(int(s), height=height, width=width, beams=beams).to_tensors() for s in seeds]
    image = torch.stack([t["image"] for t in scenes]).float()
    sparse = torch.stack([t["sparse"].reshape(1, height, width) for t in scenes]).float()
    target = torch.stack([t["target"].reshape(1, height, width) for t in scenes]).float()
    return {"image": image, "sparse": sparse, "fill": nearest_fill(sparse), "target": target}


class TinyNet(nn.Module):
    """Image + LiDAR + fill -> depth (B,1,H,W) m, confidence (B,1,H,W) >= 0, features (B,F,H,W).

    Depth is predicted as the nearest fill plus a residual; inputs are normalised by
    ``depth_scale`` metres.
    """

    def __init__(self, width: int = 16, feature_dim: int = 8, depth_scale: float = 20.0) -> None:
        super().__init__()
        self.depth_scale = depth_scale
        self.feature_dim = feature_dim
        self.body = nn.Sequential(
            nn.Conv2d(6, width, 3, padding=1), nn.ReLU(),
            nn.Conv2d(width, width, 3, padding=2, dilation=2), nn.ReLU(),
            nn.Conv2d(width, width, 3, padding=4, dilation=4), nn.ReLU(),
        )
        self.head = nn.Conv2d(width, 2 + feature_dim, 3, padding=1)

    @property
    def first_conv(self) -> nn.Conv2d:
        return self.body[0]

    def forward(self, image, sparse, fill):
        s = self.depth_scale
        x = torch.cat([image, sparse / s, (sparse > 0).to(image.dtype), fill / s], 1)
        out = self.head(self.body(x))
        depth = fill + s * 0.1 * out[:, :1]
        confidence = F.softplus(out[:, 1:2])
        features = torch.cat([image, out[:, 2:]], 1)  # colour + learned features
        return depth, confidence, features


def masked_l1(pred, target):
    valid = target > 0
    return (pred - target).abs()[valid].mean()


def build(use_crf: bool, seed: int):
    torch.manual_seed(seed)
    net = TinyNet()
    crf = CRFRefine(3 + net.feature_dim, embed_dim=8, edge_scale=1.0, sparse_weight=10.0, rtol=1e-4) \
        if use_crf else None
    return net, crf


def predict(net, crf, batch):
    depth, conf, feats = net(batch["image"], batch["sparse"], batch["fill"])
    if crf is None:
        return depth
    return crf(depth, conf, feats, batch["sparse"]).depth


def first_conv_grad_norm(net, crf, batch) -> float:
    """Gradient norm on the CNN's first conv from a loss on the CRF output only."""
    net.zero_grad()
    if crf is not None:
        crf.zero_grad()
    masked_l1(predict(net, crf, batch), batch["target"]).backward()
    g = net.first_conv.weight.grad
    return float(g.norm()) if g is not None else 0.0


def train(use_crf: bool, train_data, steps: int, *, batch_size: int = 4, lr: float = 3e-3, seed: int = 0):
    """Adam on random mini-batches (same order for both models: same seed)."""
    net, crf = build(use_crf, seed)
    params = list(net.parameters()) + (list(crf.parameters()) if crf is not None else [])
    opt = torch.optim.Adam(params, lr=lr)
    gen = torch.Generator().manual_seed(seed)
    n = train_data["image"].shape[0]
    losses = []
    for _ in range(steps):
        idx = torch.randperm(n, generator=gen)[:batch_size]
        batch = {k: v[idx] for k, v in train_data.items()}
        loss = masked_l1(predict(net, crf, batch), batch["target"])
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    return net, crf, losses


@torch.no_grad()
def evaluate(net, crf, data) -> dict[str, float]:
    pred = predict(net, crf, data)
    return average_metrics(depth_metrics(pred, data["target"]))


def run(steps: int = 150, train_scenes: int = 16, test_scenes: int = 8, *, seed: int = 0,
        height: int = 88, width: int = 304, beams: int = 16) -> dict:
    t0 = time.perf_counter()
    train_data = make_batch(range(train_scenes), height, width, beams)
    test_data = make_batch(range(1000, 1000 + test_scenes), height, width, beams)
    result = {"steps": steps, "train_scenes": train_scenes, "test_scenes": test_scenes,
              "size": [height, width], "beams": beams,
              "lidar_fraction": float((train_data["sparse"] > 0).float().mean())}
    # (a) gradients through the layer, at initialisation
    net, crf = build(True, seed)
    probe = {k: v[:2] for k, v in train_data.items()}
    result["grad_norm_first_conv_through_crf"] = first_conv_grad_norm(net, crf, probe)
    result["params_cnn"] = sum(p.numel() for p in net.parameters())
    result["params_crf"] = sum(p.numel() for p in crf.parameters())
    # (b) same CNN, same steps, same seed, with and without the layer
    fill = average_metrics(depth_metrics(test_data["fill"], test_data["target"]))
    result["nearest_fill"] = {"rmse": fill["rmse"], "mae": fill["mae"]}
    for name, use_crf in (("cnn", False), ("cnn+crf", True)):
        t = time.perf_counter()
        net, crf, losses = train(use_crf, train_data, steps, seed=seed)
        m = evaluate(net, crf, test_data)
        result[name] = {"rmse": m["rmse"], "mae": m["mae"], "train_loss_first": losses[0],
                        "train_loss_last": sum(losses[-10:]) / len(losses[-10:]),
                        "train_s": time.perf_counter() - t}
        if crf is not None:
            result[name]["learned"] = {"edge_scale": float(crf.edge_scale.detach()),
                                       "sparse_weight": float(crf.sparse_weight.detach())}
    result["total_s"] = time.perf_counter() - t0
    return result


def main(argv=None) -> None:
    parser = sa.ScriptParser(prog="layer_example.py", description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=sa.count(1), default=150)
    parser.add_argument("--train-scenes", type=sa.count(1, 10000), default=16)
    parser.add_argument("--test-scenes", type=sa.count(1, 10000), default=8)
    parser.add_argument("--beams", type=sa.count(1, 128, "LiDAR beams"), default=16)
    parser.add_argument("--seed", type=sa.seed, default=0)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    r = run(args.steps, args.train_scenes, args.test_scenes, seed=args.seed, beams=args.beams)
    print(f"{r['test_scenes']} held-out synthetic scenes {r['size'][0]}x{r['size'][1]}, {r['beams']} beams "
          f"(LiDAR on {100 * r['lidar_fraction']:.1f}% of pixels), {r['steps']} steps")
    print(f"(a) grad norm on the CNN's first conv, loss on the CRF output only: "
          f"{r['grad_norm_first_conv_through_crf']:.4g}")
    print(f"{'model':<14}{'RMSE mm':>10}{'MAE mm':>10}{'train s':>10}")
    print(f"{'nearest fill':<14}{r['nearest_fill']['rmse']:>10.1f}{r['nearest_fill']['mae']:>10.1f}{'':>10}")
    for name in ("cnn", "cnn+crf"):
        m = r[name]
        print(f"{name:<14}{m['rmse']:>10.1f}{m['mae']:>10.1f}{m['train_s']:>10.1f}")
    print(json.dumps(r))


if __name__ == "__main__":
    sys.exit(sa.run_script(main, "layer_example.py"))
