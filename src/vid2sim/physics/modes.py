"""Vibration modes of the reduced model: the linear-elastic stiffness and mass of its LBS subspace at rest.

A drop excites the lowest elastic modes, and at a fixed ν their frequencies scale as √(E/ρ), so a subspace
whose lowest Rayleigh–Ritz frequencies sit x % above the continuum's behaves as if E were (1 + x/100)² too
large. :func:`subspace_frequencies` gives those frequencies for a simulator's cubature; compare them with
:func:`vid2sim.physics.tet_modes.tet_frequencies` (quadratic tets) on the same shape. The modal training
objective of :mod:`vid2sim.physics.skinning_training` lowers them.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from vid2sim.physics.materials import lame_parameters
from vid2sim.physics.reduced import lbs_rows
from vid2sim.physics.skinning import gradient_basis
from vid2sim.physics.stiffness_curve import StiffnessCurve


def subspace_stiffness_and_mass(X: Tensor, w: Tensor, dw: Tensor, volume: float, poisson_ratio: float,
                                weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Linear-elastic stiffness and mass of the LBS subspace at rest, E = 1 and ρ = 1.

    The displacement is u(X) = Y b(X) (row-major y layout of :mod:`vid2sim.physics.reduced`) and
    ∇u_p[a, c] = Σ_l Y[a, l] G_p[c, l]. With ψ = μ ε:ε + λ/2 (tr ε)² integrated by the points (weight v_p:
    ``weights``, or volume/n each), K[(a,l),(b,m)] = Σ_p v_p (μ δ_ab Σ_c G_pcl G_pcm + μ G_pbl G_pam +
    λ G_pal G_pbm). This equals the Neo-Hookean Hessian at z = 0 (tested). M = I₃ ⊗ Σ_p v_p b_p b_pᵀ.

    Args:
        X: (n, 3) points; w: (n, H) weights; dw: (n, H, 3) their gradients (rigid column included).
        weights: (n,) integration weights (volumes); None: ``volume`` / n each.
    Returns:
        K, M: (3L, 3L) with L = 4H, differentiable in w and dw.
    """
    n = X.shape[0]
    v = (float(volume) / n) if weights is None else weights[:, None]
    mu, lam = lame_parameters(1.0, poisson_ratio)
    G = gradient_basis(X, w, dw)  # (n, 3, L)
    L = G.shape[2]
    Gf = G.reshape(n, 3 * L)
    Tp = Gf.T @ (Gf * v)  # [(a, l), (b, m)] = Σ_p v_p G_pal G_pbm
    T4 = Tp.reshape(3, L, 3, L)
    S = T4.diagonal(dim1=0, dim2=2).sum(-1)  # [l, m] = Σ_c T'[(c, l), (c, m)]
    eye3 = torch.eye(3, dtype=X.dtype, device=X.device)
    K = mu * torch.kron(eye3, S) + mu * T4.permute(2, 1, 0, 3).reshape(3 * L, 3 * L) + lam * Tp
    b = lbs_rows(X, w)
    M = torch.kron(eye3, b.T @ (b * v))
    return K, M


def subspace_frequencies(field, points: Tensor, volumes: Tensor, youngs_modulus: float, poisson_ratio: float,
                         density: float, k: int = 6) -> np.ndarray:
    """The k lowest non-rigid Rayleigh–Ritz angular frequencies ω (rad/s) of the skinning subspace.

    Args:
        field: a :class:`~vid2sim.physics.SkinningField`.
        points: (n, 3) quadrature points (a simulator's cubature points ``sim.X``); volumes: (n,) their
            integration weights (``sim.vol``). Masses are ρ·volumes, as the simulator lumps them.
    Returns:
        (k,) ω, ascending; the six rigid modes are dropped.
    """
    from scipy.linalg import eigh

    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise ValueError(f"k must be an integer >= 1, got {k!r}")
    if not (youngs_modulus > 0 and density > 0):
        raise ValueError(f"need E > 0 and density > 0, got {youngs_modulus} and {density}")
    with torch.no_grad():
        w, dw = field.weights_and_gradients(points)
        K, M = subspace_stiffness_and_mass(points, w, dw, 1.0, poisson_ratio, weights=volumes)
    Kn, Mn = K.double().cpu().numpy(), M.double().cpu().numpy()
    lam = eigh(Kn, Mn + 1e-14 * np.trace(Mn) / len(Mn) * np.eye(len(Mn)), eigvals_only=True)
    if len(lam) < k + 6:
        raise ValueError(f"the subspace has {len(lam)} degrees of freedom; k = {k} needs at least {k + 6}")
    return np.sqrt(np.clip(lam[6:6 + k], 0.0, None) * youngs_modulus / density)


def stiffness_calibration(field, points: Tensor, volumes: Tensor, vertices: Tensor | np.ndarray,
                          tets: Tensor | np.ndarray, poisson_ratio: float) -> float:
    """(ω_tets / ω_subspace)² of the lowest elastic mode: the factor ``Simulator(stiffness_scale=...)`` that makes
    the skinning subspace vibrate at the continuum's lowest frequency.

    A Rayleigh–Ritz subspace is stiffer than the continuum (its frequencies lie above), and a material fitted
    with it comes out soft by that factor. The continuum's frequency comes from quadratic tets
    (:func:`vid2sim.physics.tet_modes.tet_frequencies`) on a tet mesh of the same solid (``bench identify``: the
    FEM's rest mesh).

    Args:
        field: the skinning field; points: (K, 3) the simulator's cubature points (``sim.X``); volumes: (K,)
            their weights (``sim.vol``); vertices: (Nv, 3), tets: (Nt, 4) positively oriented, in the frame and
            units of ``points``.
    Returns:
        s ∈ (0, ∞); it does not depend on E or ρ; s < 1 when the subspace is stiffer than the tets.
    """
    from vid2sim.physics.tet_modes import tet_frequencies

    reference = tet_frequencies(vertices, tets, 1.0, poisson_ratio, 1.0, k=1, order=2)[0]
    reduced = subspace_frequencies(field, points, volumes, 1.0, poisson_ratio, 1.0, k=1)[0]
    if not (reference > 0 and reduced > 0):
        raise ValueError(f"the lowest elastic frequencies must be positive, got tets {reference}, subspace {reduced}")
    return float((reference / reduced) ** 2)


#: ν grid of :func:`stiffness_calibration_curve`: denser towards ½, where the subspace's locking grows fastest
CURVE_NUS = (0.0, 0.1, 0.2, 0.3, 0.35, 0.4, 0.43, 0.46, 0.48, 0.49)


def stiffness_calibration_curve(field, points: Tensor, volumes: Tensor, vertices: Tensor | np.ndarray,
                                tets: Tensor | np.ndarray, nus: tuple[float, ...] = CURVE_NUS
                                ) -> StiffnessCurve:
    """:func:`stiffness_calibration` at every ν of ``nus``: the factor s(ν) that makes the subspace's lowest
    frequency equal the continuum's at each ν (``Simulator(stiffness_scale=curve)``).

    The tets' frequencies come from :func:`vid2sim.physics.tet_modes.tet_frequency_curve` (three sparse
    eigensolves for the whole grid, within 1e-4 of a direct solve per ν).

    Args: as :func:`stiffness_calibration`; ``nus`` the grid (strictly increasing, in [0, 0.5)).
    Returns:
        a :class:`~vid2sim.physics.stiffness_curve.StiffnessCurve` (s interpolated between the grid's ν).
    """
    from vid2sim.physics.tet_modes import tet_frequency_curve

    reference = tet_frequency_curve(vertices, tets, nus, k=1, order=2)[:, 0]
    scales = []
    for nu, ref in zip(nus, reference):
        reduced = subspace_frequencies(field, points, volumes, 1.0, float(nu), 1.0, k=1)[0]
        if not (ref > 0 and reduced > 0):
            raise ValueError(f"the lowest elastic frequencies must be positive at nu = {nu}, got tets {ref}, "
                             f"subspace {reduced}")
        scales.append(float((ref / reduced) ** 2))
    return StiffnessCurve(tuple(nus), tuple(scales))
