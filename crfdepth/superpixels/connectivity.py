"""Connected superpixels: the last step of SLIC in torch (docs/design.md section 2).

k-means labels (:mod:`crfdepth.superpixels.slic`) may split into several pieces; here each
becomes its own 4-connected component (union-find over the horizontal runs of equal label:
hooking to the smaller root and pointer jumping), then every component smaller than
``min_size`` pixels joins the largest adjacent component if that one is larger (ties: the
one that starts first in raster order), and the segments are numbered ``0 .. S-1`` per
image. scikit-image's breadth-first pass merges such a fragment into the adjacent segment
met last instead, and cuts components above ``3 H W / n_seeds`` pixels (which SLIC at
KITTI's size does not produce); so the labels are not identical to scikit-image's, but the
segments are of the same kind. Batched, on the labels' device; the only host transfers are
the convergence tests of the union-find.
"""

from __future__ import annotations

import torch

__all__ = ["connected_segments", "union_find"]


def union_find(parent: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Roots of the graph with edges ``(a, b)``: each node's smallest connected node index.

    ``parent`` (N,) int64 starts as ``arange(N)``. Hooking roots to the smaller root
    (scatter-min) and full pointer jumping, repeated until every edge has equal roots.
    """
    while True:
        ra, rb = parent[a], parent[b]
        differ = ra != rb
        if not bool(differ.any()):
            return parent
        ra, rb = ra[differ], rb[differ]
        parent.scatter_reduce_(0, torch.maximum(ra, rb), torch.minimum(ra, rb), reduce="amin")
        while True:
            jumped = parent[parent]
            if torch.equal(jumped, parent):
                break
            parent = jumped


def connected_segments(labels: torch.Tensor, min_size: int) -> torch.Tensor:
    """(B, H, W) k-means labels -> (B, H, W) int64 connected segments ``0 .. S-1`` per image.

    Works on the horizontal runs of equal label (every row's maximal stretches), so the
    union-find has about a fifth as many nodes as there are pixels.
    """
    b, h, w = labels.shape
    device = labels.device
    # Runs: a new one starts at column 0 and wherever the label changes along the row.
    start = torch.ones(b, h, w, dtype=torch.bool, device=device)
    torch.ne(labels[:, :, 1:], labels[:, :, :-1], out=start[:, :, 1:])
    first_pixel = torch.nonzero(start.view(-1)).view(-1)  # (R,) first pixel of each run
    n_runs = first_pixel.numel()
    run = torch.cumsum(start.view(-1), 0).sub_(1).view(b, h, w)  # run index of each pixel
    run_label = labels.reshape(-1)[first_pixel]  # (R,)
    run_length = torch.diff(first_pixel, append=first_pixel.new_tensor([b * h * w]))

    # Vertical contacts between runs of consecutive rows, once per pair of runs.
    top, bottom = run[:, :-1, :], run[:, 1:, :]
    new_pair = torch.ones_like(top, dtype=torch.bool)
    new_pair[:, :, 1:] = (top[:, :, 1:] != top[:, :, :-1]) | (bottom[:, :, 1:] != bottom[:, :, :-1])
    pair = torch.nonzero(new_pair.view(-1)).view(-1)
    top, bottom = top.reshape(-1)[pair], bottom.reshape(-1)[pair]
    same = run_label[top] == run_label[bottom]

    # 1. Connected components: union-find on the runs over the same-label contacts.
    root = union_find(torch.arange(n_runs, device=device), top[same], bottom[same])

    # 2. Merge small components into their largest neighbour, if that one is larger.
    size = torch.zeros(n_runs, dtype=torch.int64, device=device).index_add_(0, root, run_length)
    # Horizontal neighbours: consecutive runs of a row; vertical: the other contacts.
    row_first = torch.zeros(n_runs, dtype=torch.bool, device=device)
    row_first[run[:, :, 0].reshape(-1)] = True
    left = torch.nonzero(~row_first[1:]).view(-1)  # run `left` touches run `left + 1`
    differ = ~same
    ca = torch.cat([root[left], root[top[differ]]])
    cb = torch.cat([root[left + 1], root[bottom[differ]]])
    u, v = torch.cat([ca, cb]), torch.cat([cb, ca])  # both directions: u's candidate is v
    ids = torch.arange(n_runs, device=device)
    key = size * n_runs + (n_runs - 1 - ids)  # larger first, then the one starting first
    best = torch.full((n_runs,), -1, dtype=torch.int64, device=device)
    best.scatter_reduce_(0, u, key[v], reduce="amax")
    merge = (size < min_size) & (best > key)  # only roots have size > 0
    target = torch.where(merge, n_runs - 1 - best % n_runs, ids)
    while True:  # follow chains small -> larger -> ...; keys increase, so no cycles
        jumped = target[target]
        if torch.equal(jumped, target):
            break
        target = jumped
    final = target[root]  # (R,) the root run of each run's segment

    # 3. Consecutive numbers per image, in the order of the segments' root runs.
    present = torch.zeros(n_runs, dtype=torch.bool, device=device)
    present[final] = True
    number = torch.cumsum(present, 0)  # 1 + index of each present root among all frames
    frame_first = run[:, 0, 0]  # first run of each frame
    frame_of_run = torch.zeros(n_runs, dtype=torch.int64, device=device)
    frame_of_run[frame_first[1:]] = 1
    frame_of_run = torch.cumsum(frame_of_run, 0)
    before = number[frame_first] - present[frame_first].to(torch.int64)  # roots of earlier frames
    run_number = number[final] - 1 - before[frame_of_run]
    return run_number[run]
