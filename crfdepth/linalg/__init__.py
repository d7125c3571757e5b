"""Sparse SPD solves for graph-Laplacian systems, differentiable by implicit adjoints."""

from crfdepth.linalg.adjoint import solve_system
from crfdepth.linalg.diagnostics import SolveInfo, SolverSettings
from crfdepth.linalg.operators import grid_edge_index
from crfdepth.linalg.solve import solve_grid_laplacian, solve_laplacian, solver_settings
from crfdepth.linalg.system import System

__all__ = ["SolveInfo", "SolverSettings", "System", "grid_edge_index", "solve_grid_laplacian", "solve_laplacian",
           "solve_system", "solver_settings"]
