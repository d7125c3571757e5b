"""The energy and the system the potentials assemble (crfdepth/potentials/energy.py)."""

from __future__ import annotations

import torch

from crfdepth.potentials.energy import (
    EnergyTerms,
    PotentialWeights,
    data_confidence,
    energy,
    graph_system,
    grid_potentials,
    grid_system,
    to_depth,
    to_unknown,
)


def _terms(seed=0, n=6):
    g = torch.Generator().manual_seed(seed)
    f = dict(generator=g, dtype=torch.float64)
    edge_index = torch.tensor([[0, 1, 2, 3, 4, 0], [1, 2, 3, 4, 5, 5]])
    e = edge_index.shape[1]
    return EnergyTerms(torch.rand(n, **f) * 20, torch.rand(n, **f), torch.rand(n, **f) * 20, edge_index,
                       torch.rand(e, **f), torch.rand(e, **f), torch.rand(e, **f), *torch.rand(5, **f).unbind())


def test_the_system_is_the_energy_s_gradient_so_its_solution_minimises_it():
    terms = _terms()
    system = graph_system(terms)
    x = torch.randn(6, dtype=torch.float64, requires_grad=True)
    energy(x, terms)["total"].backward()
    A = torch.diag(system.diagonal).clone()
    src, dst = terms.edge_index
    w = system.weights[0]
    A.index_put_((src, src), w, accumulate=True)
    A.index_put_((dst, dst), w, accumulate=True)
    A.index_put_((src, dst), -w, accumulate=True)
    A.index_put_((dst, src), -w, accumulate=True)
    assert torch.allclose(x.grad, 2 * (A @ x.detach() - system.rhs), rtol=1e-10)  # dE/dx = 2 (A x - b)
    minimiser = torch.linalg.solve(A, system.rhs).requires_grad_()
    energy(minimiser, terms)["total"].backward()
    assert float(minimiser.grad.abs().max()) < 1e-9


def test_a_potential_that_is_off_adds_nothing():
    terms = _terms()
    parts = energy(torch.zeros(6, dtype=torch.float64), EnergyTerms(**{**terms.__dict__, "normal": None}))
    assert float(parts["normal"]) == 0.0 and float(parts["total"]) > 0


def test_data_confidence_grows_with_the_count_and_halves_at_one_return():
    w = data_confidence(torch.tensor([0.0, 1.0, 3.0, 99.0]), torch.tensor(10.0))
    assert torch.allclose(w, torch.tensor([0.0, 5.0, 7.5, 9.9]), rtol=1e-6)


def test_the_unknown_maps_back_to_depth_and_keeps_empty_pixels_empty():
    depth = torch.tensor([0.0, 2.0, 40.0], dtype=torch.float64)
    for variable in ("depth", "inverse", "log"):
        unknown = to_unknown(depth, variable)
        assert float(unknown[0]) == 0.0
        assert torch.allclose(to_depth(unknown[1:], variable), depth[1:], rtol=1e-12)


def test_grid_potentials_give_a_system_with_one_weight_per_neighbour_pair():
    h, w = 4, 5
    image = torch.rand(1, 3, h, w, generator=torch.Generator().manual_seed(0))
    sparse = torch.zeros(1, 1, h, w)
    sparse[0, 0, ::2, ::2] = 10.0
    K = torch.tensor([[[50.0, 0, w / 2], [0, 50.0, h / 2], [0, 0, 1]]])
    weights = PotentialWeights(torch.tensor(0.5), torch.tensor(0.5), None, None, torch.tensor(100.0),
                               torch.tensor(0.1), torch.tensor(0.3), torch.tensor(1.0))
    t = grid_potentials(image, sparse, K, sparse.clamp_min(1.0), torch.tensor(0.01), None, weights)
    system = grid_system(t)
    assert system.is_grid and system.weights[0].shape == (1, h, w - 1) and system.weights[1].shape == (1, h - 1, w)
    assert t.normal is None and t.distance is None  # no geometry in a first pass
    data = 0.5 * t.w
    assert torch.allclose(system.diagonal, data + 0.01) and bool((t.w[0, ::2, ::2] > 0).all())
    assert float(t.w[0, 1, 1]) == 0.0
