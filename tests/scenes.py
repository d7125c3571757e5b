"""Small hand-made scenes that several test files share."""

from __future__ import annotations

import torch


def leaky_wall(leak_columns=((30, 32), (58, 60))):
    """A box at 8 m in front of a wall at 25 m, scan lines every 4 rows, with wall returns
    leaked into the box's columns ``[a, b)`` of ``leak_columns`` on every scan line through it
    (by default 2 px at both edges: the gate's default window, 5 px, sees a foreground
    return within 2 px)."""
    h, w = 48, 96
    K = torch.tensor([[720.0, 0, w / 2], [0, 720.0, h / 2], [0, 0, 1]])
    truth = torch.full((h, w), 25.0)
    truth[12:40, 30:60] = 8.0
    image = torch.full((1, 3, h, w), 0.8)
    image[:, :, 12:40, 30:60] = 0.2
    sparse = torch.zeros(h, w)
    sparse[2::4] = truth[2::4]  # scan lines every 4 rows, a return in every column
    leaked = torch.zeros(h, w, dtype=torch.bool)
    for a, b in leak_columns:
        leaked[14:38:4, a:b] = True
    sparse[leaked] = 25.0
    return image, sparse[None, None], K, truth, leaked


def table4_frames(kitti_root, samples: int, step: int = 1):
    """Every ``step``-th raw KITTI frame of ``kitti_root`` as the paper's Table 4 scores it (as
    ``benchmarks/accuracy_parts/protocols.table4_input`` makes it): ``samples`` pixels of the projected scan in
    the bottom-centre 912 x 228 as the input, the whole scan (its held-out points included) as the target."""
    import dataclasses

    from crfdepth.data.factory import build_dataset
    from crfdepth.data.sampling import kitti_table4

    raw = build_dataset("raw", kitti_root / "raw", holdout="fraction", holdout_fraction=0.2, clean_target=False)
    for i in range(0, len(raw), step):
        s = raw[i]
        whole = torch.where(s.sparse > 0, s.sparse, s.target)
        yield kitti_table4(samples, seed=0)(dataclasses.replace(s, target=whole))


def table4_scores(models: dict, frames) -> dict:
    """name -> (mean RMSE m, mean REL) of each model of ``models`` over ``frames`` (Table 4 samples,
    :func:`table4_frames`), per image then averaged."""
    scores = {name: [] for name in models}
    for t in frames:
        valid = t.target > 0
        for name, model in models.items():
            with torch.no_grad():
                depth = model(t.image[None], t.sparse[None], t.K[None]).depth[0]
            err = depth[valid] - t.target[valid]
            scores[name].append((float(err.pow(2).mean().sqrt()), float((err.abs() / t.target[valid]).mean())))
    return {name: tuple(sum(v[j] for v in rows) / len(rows) for j in (0, 1)) for name, rows in scores.items()}
