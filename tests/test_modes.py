"""Vibration modes of tet meshes: exact element integrals, analytic bar frequencies, and convergence."""

import math

import numpy as np
import pytest

from vid2sim.meshing.tetra import box_tet_mesh
from vid2sim.physics.sparse_lu import SymmetricLU, nested_dissection
from vid2sim.physics.tet_modes import (
    LOCAL_MODE_PARTICIPATION,
    lowest_elastic_modes,
    mode_participation,
    quadratic_tet_nodes,
    reference_mass,
    rigid_modes,
    tet_frequencies,
    tet_frequency_curve,
    tet_stiffness_and_mass,
)

BAR = (2.0, 0.4, 0.4)  # a free 2 m bar of 0.4 m square section; E = ρ = 1, ν = 0.3
NU = 0.3


def _bar(res):
    m = box_tet_mesh(BAR, res)
    return m.vertices, m.tets


def test_reference_mass_is_exact():
    # linear tets: ∫ N_a N_b dV = V (1 + δ_ab) / 20
    assert np.allclose(reference_mass(1), (np.ones((4, 4)) + np.eye(4)) / 20)
    M2 = reference_mass(2)
    # partition of unity: Σ_ab ∫ N_a N_b = ∫ 1 = V; known entries: corner–corner 1/70 … (Zienkiewicz)
    assert M2.sum() == pytest.approx(1.0, rel=1e-14)
    assert M2[0, 0] == pytest.approx(6 / 420) and M2[0, 1] == pytest.approx(1 / 420)
    assert M2[4, 4] == pytest.approx(32 / 420) and M2[0, 4] == pytest.approx(-4 / 420)
    assert np.allclose(M2, M2.T) and np.all(np.linalg.eigvalsh(M2) > 0)


def test_quadratic_nodes_are_shared_edge_midpoints():
    X, T = _bar((2, 1, 1))
    nodes, elements = quadratic_tet_nodes(X, T)
    edges = {tuple(sorted((int(t[i]), int(t[j])))) for t in T.numpy() for i in range(4) for j in range(i + 1, 4)}
    assert len(nodes) == len(X) + len(edges)
    assert np.array_equal(elements[:, :4], T.numpy())
    Xn = X.numpy()
    for e, (i, j) in enumerate(((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))):
        assert np.allclose(nodes[elements[:, 4 + e]], 0.5 * (Xn[T[:, i]] + Xn[T[:, j]]))


def test_quadratic_tets_match_the_analytic_bar():
    """Saint-Venant torsion ω = (π/L)√(G J / (ρ I_p)) with J = 0.140577 a⁴ and I_p = a⁴/6, the free rod's
    axial ω = (π/L)√(E/ρ) (its Poisson/Love correction here is −0.3 %), and bending below Euler–Bernoulli's
    4.730² √(E I / (ρ A L⁴)) by the shear and rotary inertia of a slenderness-5 bar."""
    L, a = BAR[0], BAR[1]
    G = 1.0 / (2 * (1 + NU))
    torsion = math.pi / L * math.sqrt(G * 0.140577 * 6)
    axial = math.pi / L
    bending = 4.730**2 * math.sqrt(a**2 / 12 / L**4)
    w = tet_frequencies(*_bar((20, 4, 4)), 1.0, NU, 1.0, k=6, order=2)
    assert w[0] == pytest.approx(w[1], rel=1e-3)  # the two bending directions of a square section
    assert 0.85 < w[0] / bending < 0.95
    assert w[2] == pytest.approx(torsion, rel=5e-3)
    assert w[5] == pytest.approx(axial, rel=1e-2)
    assert w[3] == pytest.approx(w[4], rel=1e-3)  # second bending pair
    # every frequency scales as √(E/ρ)
    assert np.allclose(tet_frequencies(*_bar((20, 4, 4)), 9.0, NU, 4.0, k=6, order=2), 1.5 * w, rtol=1e-6)


def test_quadratic_tets_converge_where_linear_tets_lock():
    coarse, fine = _bar((10, 2, 2)), _bar((20, 4, 4))
    p1 = tet_frequencies(*coarse, 1.0, NU, 1.0, k=6, order=1)
    p2 = tet_frequencies(*coarse, 1.0, NU, 1.0, k=6, order=2)
    p2_fine = tet_frequencies(*fine, 1.0, NU, 1.0, k=6, order=2)
    assert np.all(p2 <= p1 * (1 + 1e-9))  # order 2's space holds order 1's: Rayleigh–Ritz
    assert np.all(np.abs(p2[:2] / p2_fine[:2] - 1) < 5e-3)
    assert np.all(p1[:2] / p2_fine[:2] > 1.2)  # linear tets lock in bending on this mesh
    # lumping the mass lowers linear tets' frequencies, but far from enough to undo the locking
    lumped = tet_frequencies(*coarse, 1.0, NU, 1.0, k=6, order=1, lumped=True)
    assert np.all(lumped < p1) and np.all(lumped[:2] / p2_fine[:2] > 1.1)


def test_the_frequency_curve_over_nu_matches_direct_solves():
    """Rayleigh–Ritz on the modes of three solved ν: within 1e-4 of a direct solve at every ν of the grid,
    exact at the solved ones, and never below (upper bounds)."""
    nus = (0.0, 0.2, 0.3, 0.4, 0.45, 0.49)
    X, T = _bar((10, 2, 2))
    curve = tet_frequency_curve(X, T, nus, k=3)
    assert curve.shape == (6, 3)
    for nu, row in zip(nus, curve):
        direct = tet_frequencies(X, T, 1.0, nu, 1.0, k=3, order=2)
        assert np.all(row >= direct * (1 - 1e-9)) and np.all(row <= direct * (1 + 1e-4)), (nu, row, direct)
        if nu in (0.0, 0.49):
            assert np.allclose(row, direct, rtol=1e-9)
    with pytest.raises(ValueError, match="poisson_ratios"):
        tet_frequency_curve(X, T, (0.3, 0.5))
    with pytest.raises(ValueError, match="anchors"):
        tet_frequency_curve(X, T, (0.3,), anchors=1)


def _cube_with_fin(fin_cells=8):
    """A free 0.6 m cube (6³ cells) with a 0.1 × 0.1 m fin of ``fin_cells`` cells on one face (the fin 3.6 % of
    the mass at 8 cells), on one conforming structured mesh; and the cube's mesh alone."""
    cube = box_tet_mesh((0.6, 0.6, 0.6), (6, 6, 6))
    fin = box_tet_mesh((0.1 * fin_cells, 0.1, 0.1), (fin_cells, 1, 1), origin=(0.6, 0.2, 0.2))
    V = np.concatenate([cube.vertices.numpy(), fin.vertices.numpy()])
    T = np.concatenate([cube.tets.numpy(), fin.tets.numpy() + len(cube.vertices)])
    _, first, index = np.unique(np.round(V / 0.05).astype(np.int64), axis=0, return_index=True, return_inverse=True)
    return V[first], index.ravel()[T], cube


def test_mode_participation_is_the_share_of_the_mass_a_mode_moves():
    """1 for a translation; the part's share of the (diagonal) mass for a translation of a part alone; the fin's
    own bending modes, the lowest of the cube with its fin, move under 3 % of its mass."""
    V, T, _ = _cube_with_fin()
    K, M, nodes = tet_stiffness_and_mass(V, T, 1.0, 0.3, 1.0, order=2)
    translation = rigid_modes(nodes)[:, :1]
    assert mode_participation(translation, M)[0] == pytest.approx(1.0, rel=1e-12)
    on_fin = np.zeros_like(translation)
    fin = np.repeat(nodes[:, 0] > 0.6 + 1e-9, 3)
    on_fin[fin, 0] = 1.0  # the fin beyond the cube's face translates, the rest stays
    m = M.diagonal().reshape(-1, 3).mean(1)
    assert mode_participation(on_fin, M)[0] == pytest.approx(m[nodes[:, 0] > 0.6 + 1e-9].sum() / m.sum(), rel=1e-12)
    w2, vectors = lowest_elastic_modes(K, M, nodes, 4)
    share = mode_participation(vectors, M)
    assert np.all(share[:2] < 0.03) and share.shape == (4,)  # the fin's two bending modes come first


def test_the_frequency_curve_leaves_out_a_fin_s_local_modes():
    """A fin on a cube vibrates alone far below the cube (0.17 against 2.96 rad/s at E = ρ = 1): with
    ``min_participation`` the curve skips its modes (recorded in ``left_out``) and gives the cube's own modes, within
    2 % of the cube without the fin; without it the fin's modes come first. The fin has nine modes below the cube's
    third, more than the first room left for them: the room is doubled until they fit."""
    V, T, cube = _cube_with_fin()
    every = tet_frequency_curve(V, T, (0.3,), k=3)
    left_out = []
    body = tet_frequency_curve(V, T, (0.3,), k=3, min_participation=LOCAL_MODE_PARTICIPATION, left_out=left_out)
    alone = tet_frequency_curve(cube.vertices, cube.tets, (0.3,), k=3)
    assert every[0, 0] < 0.2 < 2.9 < alone[0, 0]
    np.testing.assert_allclose(body, alone, rtol=0.02)
    assert len(left_out) == 1 and left_out[0]["nu"] == 0.3 and len(left_out[0]["omega"]) == 9
    assert left_out[0]["omega"][:3] == pytest.approx(every[0].tolist(), rel=1e-6)
    assert max(left_out[0]["participation"]) < LOCAL_MODE_PARTICIPATION
    assert np.array_equal(tet_frequency_curve(V, T, (0.3,), k=3, min_participation=0.0), every)
    with pytest.raises(ValueError, match="min_participation"):
        tet_frequency_curve(V, T, (0.3,), k=3, min_participation=1.0)


def test_bad_inputs():
    X, T = _bar((2, 1, 1))
    with pytest.raises(ValueError, match="lumped mass is for linear tets"):
        tet_frequencies(X, T, 1.0, NU, 1.0, order=2, lumped=True)
    with pytest.raises(ValueError, match="order must be"):
        tet_frequencies(X, T, 1.0, NU, 1.0, order=3)
    with pytest.raises(ValueError, match="k must be"):
        tet_frequencies(X, T, 1.0, NU, 1.0, k=0)
    with pytest.raises(ValueError, match="nu < 0.5"):
        tet_frequencies(X, T, 1.0, 0.5, 1.0)
    with pytest.raises(ValueError, match="tet indices"):
        tet_frequencies(X, T + 1000, 1.0, NU, 1.0)
    with pytest.raises(ValueError, match="non-positive volume"):
        tet_frequencies(X, T[:, [1, 0, 2, 3]], 1.0, NU, 1.0)


def test_lowest_elastic_modes_match_a_dense_solve():
    """The shift-invert Lanczos with the nested-dissection LU and rigid deflation against LAPACK on the full
    dense pencil, on a free bar whose spectrum has degenerate bending pairs (a cluster Lanczos can split)."""
    from scipy.linalg import eigh

    K, M, nodes = tet_stiffness_and_mass(*_bar((6, 2, 2)), 1.0, NU, 1.0, order=2)
    R = rigid_modes(nodes)
    assert np.abs(K @ R).max() < 1e-10 * abs(K).max()  # the six rigid motions cost no energy
    dense = eigh(K.toarray(), M.toarray(), eigvals_only=True)[6:14]
    w2, phi = lowest_elastic_modes(K.tocsc(), M.tocsc(), nodes, 8)
    assert np.allclose(w2, dense, rtol=1e-9)
    assert np.allclose(phi.T @ (M @ phi), np.eye(8), atol=1e-8)  # M-orthonormal
    assert np.abs(R.T @ (M @ phi)).max() < 1e-8  # and free of rigid motion
    assert np.allclose(K @ phi, (M @ phi) * w2, atol=1e-8 * w2.max())


def test_lowest_elastic_modes_of_a_few_tets_are_solved_densely():
    """One quadratic tet (30 DOF) has no room for Lanczos beyond its rigid modes; the dense path gives the
    pencil's eigenpairs, free of rigid motion."""
    X = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    K, M, nodes = tet_stiffness_and_mass(X, np.array([[0, 1, 2, 3]]), 1.0, NU, 1.0, order=2)
    w2, phi = lowest_elastic_modes(K, M, nodes, 3)
    assert w2.shape == (3,) and (w2 > 1e-6).all() and np.allclose(K @ phi, (M @ phi) * w2, atol=1e-9)
    assert np.abs(rigid_modes(nodes).T @ (M @ phi)).max() < 1e-9


def test_nested_dissection_keeps_each_node_s_components_together_and_cuts_the_fill():
    import scipy.sparse.linalg as spla

    K, M, nodes = tet_stiffness_and_mass(*_bar((12, 3, 3)), 1.0, NU, 1.0, order=2)
    A = (K + M).tocsc()
    order = nested_dissection(A)
    assert np.array_equal(np.sort(order), np.arange(K.shape[0]))  # a permutation
    assert np.array_equal(order[1::3], order[0::3] + 1) and np.array_equal(order[2::3], order[0::3] + 2)
    lu = SymmetricLU(A, order)
    assert lu.positive_definite and not SymmetricLU((K - M).tocsc(), order).positive_definite
    b = np.random.default_rng(0).standard_normal((A.shape[0], 2))
    assert np.allclose(A @ lu.solve(b), b, atol=1e-9) and np.allclose(A @ lu.solve(b[:, 0]), b[:, 0], atol=1e-9)
    natural = spla.splu(A, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    assert lu.fill < 0.5 * (natural.L.nnz + natural.U.nnz)
    with pytest.raises(ValueError, match="multiple"):
        nested_dissection(A[:-1, :-1])


def test_bench_speed_modes_section_agrees_with_its_baseline():
    from vid2sim.apps.bench.modes_speed import run

    out = run(quick=True)
    assert out["modes_tets"] > 500 and out["modes_dof"] > 3000
    assert out["modes_max_relative_difference"] < 1e-8  # the same six frequencies as SciPy's own shift-invert
    assert out["modes_seconds"] > 0 and out["modes_speedup"] == pytest.approx(
        out["modes_seconds_superlu_mmd"] / out["modes_seconds"])
