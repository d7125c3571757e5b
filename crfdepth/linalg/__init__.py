"""Sparse SPD solves for graph-Laplacian systems, differentiable by implicit adjoints."""

from crfdepth.linalg.operators import grid_edge_index
from crfdepth.linalg.solve import SolveInfo, solve_grid_laplacian, solve_laplacian

__all__ = ["SolveInfo", "grid_edge_index", "solve_grid_laplacian", "solve_laplacian"]
