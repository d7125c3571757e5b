"""Benchmark of the differentiable Laplacian solve (issue: foundation; docs/design.md section 4).

Two systems, ``A = diag(d) + L(w)`` with 5% of the nodes observed (``d = 1`` there,
``eps = 1e-3`` elsewhere), random weights in [0.05, 1], random ``z`` on observed nodes:

- ``superpixel``: 5,500 nodes (55 x 100 layout, 4 neighbours each) through the general
  edge-list path (:func:`crfdepth.linalg.solve_laplacian`);
- ``pixel``: the 1216 x 352 KITTI grid (428,032 nodes, 4-connected) through the grid
  fast path (:func:`crfdepth.linalg.solve_grid_laplacian`).

For each: forward and backward time (median of repeats) of crfdepth's CG from a zero start
at rtol 1e-6, iterations and final relative residual; scipy's ``cg`` (Jacobi, same rtol)
and ``spsolve`` on the same matrix; and peak memory of the implicit backward against
autograd unrolled through the same CG iterations (each measured in a fresh process from
the growth of its resident set; on CUDA from the allocator's peak). Prints a table and
one JSON line per system.

    python benchmarks/solver.py [--dtype float64|float32] [--device cpu|cuda] [--repeats 5]
"""

from __future__ import annotations

import json
import multiprocessing as mp
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from crfdepth.linalg import grid_edge_index, solve_grid_laplacian, solve_laplacian

if str(Path(__file__).resolve().parent) not in sys.path:  # a load by the file's path (the tests) has not
    sys.path.append(str(Path(__file__).resolve().parent))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)

RTOL = 1e-6
EPS = 1e-3


def make_system(kind: str, dtype: torch.dtype, device: str, seed: int = 0) -> dict:
    gen = torch.Generator().manual_seed(seed)
    if kind == "superpixel":
        rows, cols = 55, 100
    else:
        rows, cols = 352, 1216
    n = rows * cols
    observed = torch.rand(n, generator=gen) < 0.05
    d = torch.where(observed, 1.0, EPS).to(dtype)
    z = torch.rand(n, generator=gen, dtype=torch.float64).to(dtype) * 50 + 5
    x_prior = torch.full((n,), 20.0, dtype=dtype)
    b = d * torch.where(observed, z, x_prior)
    ei = grid_edge_index(rows, cols)
    w = (torch.rand(ei.shape[1], generator=gen, dtype=torch.float64) * 0.95 + 0.05).to(dtype)
    return dict(kind=kind, rows=rows, cols=cols, n=n, b=b.to(device), d=d.to(device),
                edge_index=ei.to(device), w=w.to(device))


def crf_solve(s: dict, b, d, w, max_iter=20000):
    """Solve through the public API; grid fast path for the pixel system."""
    if s["kind"] == "pixel":
        r, c = s["rows"], s["cols"]
        nh = r * (c - 1)
        x, info = solve_grid_laplacian(b.view(1, r, c), d.view(1, r, c), w[:nh].view(1, r, c - 1),
                                       w[nh:].view(1, r - 1, c), rtol=RTOL, max_iter=max_iter)
        return x.reshape(-1), info
    return solve_laplacian(b, d, s["edge_index"], w, rtol=RTOL, max_iter=max_iter)


def scipy_matrix(s: dict) -> sp.csr_matrix:
    ei = s["edge_index"].cpu().numpy()
    w = s["w"].double().cpu().numpy()
    n = s["n"]
    L = sp.coo_matrix((np.concatenate([-w, -w]), (np.concatenate([ei[0], ei[1]]), np.concatenate([ei[1], ei[0]]))),
                      shape=(n, n)).tocsr()
    deg = -np.asarray(L.sum(axis=1)).ravel()
    return (L + sp.diags(deg + s["d"].double().cpu().numpy())).tocsr()


def sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def timed(fn, repeats: int, device: str) -> tuple[float, object]:
    out = fn()
    times = []
    for _ in range(repeats):
        sync(device)
        t = time.perf_counter()
        out = fn()
        sync(device)
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def unrolled_pcg(s: dict, b, d, w, iters: int):
    """Jacobi PCG written with plain differentiable ops: autograd records every iteration."""
    ei = s["edge_index"]
    src, dst = ei
    deg = torch.zeros_like(d).index_add(0, src, w).index_add(0, dst, w)
    diag = d + deg

    def matvec(v):
        diff = (v[src] - v[dst]) * w
        return d * v + torch.zeros_like(v).index_add(0, src, diff).index_add(0, dst, -diff)

    x = torch.zeros_like(b)
    r = b.clone()
    z = r / diag
    p = z
    rz = torch.dot(r, z)
    for _ in range(iters):
        q = matvec(p)
        alpha = rz / torch.dot(p, q)
        x = x + alpha * p
        r = r - alpha * q
        z = r / diag
        rz_new = torch.dot(r, z)
        p = z + (rz_new / rz) * p
        rz = rz_new
    return x


def _rss_mb(field: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field):
                return int(line.split()[1]) / 1024
    return float("nan")


def _fwd_bwd(s, mode, iters, dtype, device):
    b = s["b"].clone().requires_grad_()
    d = s["d"].clone().requires_grad_()
    w = s["w"].clone().requires_grad_()
    g = torch.randn(s["n"], dtype=dtype, device=device)
    x = crf_solve(s, b, d, w)[0] if mode == "implicit" else unrolled_pcg(s, b, d, w, iters)
    (x * g).sum().backward()


def _peak_worker(kind, dtype_name, device, mode, iters, queue):
    import ctypes

    torch.set_num_threads(2)
    dtype = getattr(torch, dtype_name)
    s = make_system(kind, dtype, device)
    # One untimed run first, so that one-off allocations (kernels, thread pools, lazy
    # library state) are not counted; then hand freed memory back to the OS.
    _fwd_bwd(s, mode, min(iters, 2), dtype, device)
    if device == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
    else:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        with open("/proc/self/clear_refs", "w") as f:  # reset the peak-RSS counter
            f.write("5")
        base = _rss_mb("VmRSS")
    _fwd_bwd(s, mode, iters, dtype, device)
    if device == "cuda":
        torch.cuda.synchronize()
        peak = (torch.cuda.max_memory_allocated() - base) / 2**20
    else:
        peak = _rss_mb("VmHWM") - base
    queue.put(peak)


def peak_mb(kind, dtype_name, device, mode, iters) -> float:
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=_peak_worker, args=(kind, dtype_name, device, mode, iters, q))
    p.start()
    value = q.get()
    p.join()
    return value


def run(kind: str, dtype_name: str, device: str, repeats: int, unrolled_cap: int) -> dict:
    dtype = getattr(torch, dtype_name)
    s = make_system(kind, dtype, device)
    b = s["b"].clone().requires_grad_()
    d = s["d"].clone().requires_grad_()
    w = s["w"].clone().requires_grad_()
    g = torch.randn(s["n"], dtype=dtype, device=device, generator=None)

    fwd_s, (x, info) = timed(lambda: crf_solve(s, b.detach(), d.detach(), w.detach()), repeats, device)

    def fwd_bwd():
        xx, inf = crf_solve(s, b, d, w)
        return xx, inf

    def bwd():
        xx, inf = fwd_bwd()
        sync(device)
        t = time.perf_counter()
        (xx * g).sum().backward()
        sync(device)
        return time.perf_counter() - t, inf

    bwd()
    bwd_times, infos = [], []
    for _ in range(repeats):
        t, inf = bwd()
        bwd_times.append(t)
        infos.append(inf)
    bwd_s = statistics.median(bwd_times)
    adj = infos[-1].adjoint

    A = scipy_matrix(s)
    bn = s["b"].double().cpu().numpy()
    M = sp.diags(1.0 / A.diagonal())
    scipy_iters = [0]

    def count(_):
        scipy_iters[0] += 1

    def scipy_cg():
        scipy_iters[0] = 0
        return spla.cg(A, bn, rtol=RTOL, M=M, maxiter=20000, callback=count)

    scipy_cg_s, (xs, _) = timed(scipy_cg, max(1, repeats // 2), "cpu")
    spsolve_s, xd = timed(lambda: spla.spsolve(A.tocsc(), bn), 1, "cpu")
    iters = int(info.iterations.max())
    unrolled_iters = min(iters, unrolled_cap)
    implicit_peak = peak_mb(kind, dtype_name, device, "implicit", 0)
    unrolled_peak = peak_mb(kind, dtype_name, device, "unrolled", unrolled_iters)
    x_np = x.double().cpu().numpy()
    return {
        "system": kind, "nodes": s["n"], "edges": int(s["edge_index"].shape[1]), "dtype": dtype_name,
        "device": device, "fwd_s": fwd_s, "bwd_s": bwd_s, "iters": iters,
        "adjoint_iters": int(adj.iterations.max()), "rel_residual": float(info.rel_residual.max()),
        "scipy_cg_s": scipy_cg_s, "scipy_cg_iters": scipy_iters[0], "spsolve_s": spsolve_s,
        "max_abs_diff_vs_spsolve": float(np.abs(x_np - xd).max()),
        "implicit_peak_mb": round(implicit_peak, 2), "unrolled_peak_mb": round(unrolled_peak, 2),
        "unrolled_iters": unrolled_iters,
        "fwd_over_scipy_cg": fwd_s / scipy_cg_s, "bwd_over_fwd": bwd_s / fwd_s,
        "unrolled_over_implicit_mem": unrolled_peak / max(implicit_peak, 1e-9),
    }


def main(argv=None) -> None:
    parser = sa.ScriptParser(prog="solver.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    parser.add_argument("--device", type=sa.device, default="cpu")
    parser.add_argument("--repeats", type=sa.count(1), default=5)
    parser.add_argument("--systems", nargs="+", default=["superpixel", "pixel"], choices=["superpixel", "pixel"])
    parser.add_argument("--unrolled-cap", type=sa.count(1, 100000), default=300,
                        help="most CG iterations to unroll (unrolling thousands of pixel-grid "
                             "iterations needs tens of GB); the JSON says how many were used")
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    rows = [run(k, args.dtype, args.device, args.repeats, args.unrolled_cap) for k in args.systems]
    head = ("system", "nodes", "fwd_s", "bwd_s", "iters", "rel_residual", "scipy_cg_s", "spsolve_s",
            "implicit_peak_mb", "unrolled_peak_mb", "unrolled_iters")
    print(f"solver benchmark ({args.dtype}, {args.device}, rtol {RTOL:g}, torch threads {torch.get_num_threads()})")
    print(" | ".join(f"{h:>14}" for h in head))
    for r in rows:
        print(" | ".join(f"{r[h]:>14.4g}" if isinstance(r[h], float) else f"{r[h]:>14}" for h in head))
    for r in rows:
        print(f"  {r['system']}: fwd/scipy_cg {r['fwd_over_scipy_cg']:.2f} (target <= 1.0), bwd/fwd "
              f"{r['bwd_over_fwd']:.2f} (target <= 1.3), unrolled/implicit memory "
              f"{r['unrolled_over_implicit_mem']:.1f}x over {r['unrolled_iters']} of {r['iters']} iterations "
              f"(target >= 10)")
    for r in rows:
        print(json.dumps(r))


if __name__ == "__main__":
    sys.exit(sa.run_script(main, "solver.py"))
