"""Sparse SPD solves for graph-Laplacian systems, differentiable by implicit adjoints."""

from crfdepth.linalg.adjoint import SolveInfo
from crfdepth.linalg.operators import grid_edge_index
from crfdepth.linalg.solve import solve_grid_laplacian, solve_laplacian, solver_settings

__all__ = ["SolveInfo", "grid_edge_index", "solve_grid_laplacian", "solve_laplacian", "solver_settings"]
