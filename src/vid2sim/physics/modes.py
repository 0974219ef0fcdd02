"""Vibration modes of the reduced model: the linear-elastic stiffness and mass of its LBS subspace at rest.

A drop excites the lowest elastic modes, and at a fixed ν their frequencies scale as √(E/ρ), so a subspace
whose lowest Rayleigh–Ritz frequencies sit x % above the continuum's behaves as if E were (1 + x/100)² too
large. :func:`subspace_frequencies` gives those frequencies for a simulator's cubature; compare them with
:func:`vid2sim.physics.tet_modes.tet_frequencies` (quadratic tets) on the same shape. The modal training
objective of :mod:`vid2sim.physics.skinning_training` lowers them.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from vid2sim.physics.materials import lame_parameters
from vid2sim.physics.reduced import lbs_rows
from vid2sim.physics.skinning import gradient_basis, gradient_basis_unchecked
from vid2sim.physics.stiffness_curve import StiffnessCurve
from vid2sim.physics.tet_modes import tet_frequencies, tet_frequency_curve
from vid2sim.physics.volumetric import projection_basis


def subspace_stiffness_and_mass(X: Tensor, w: Tensor, dw: Tensor, volume: float, poisson_ratio: float,
                                weights: Tensor | None = None, volumetric: str = "pointwise",
                                trusted: bool = False) -> tuple[Tensor, Tensor]:
    """Linear-elastic stiffness and mass of the LBS subspace at rest, E = 1 and ρ = 1.

    The displacement is u(X) = Y b(X) (row-major y layout of :mod:`vid2sim.physics.reduced`) and
    ∇u_p[a, c] = Σ_l Y[a, l] G_p[c, l]. With ψ = μ ε:ε + λ/2 (tr ε)² integrated by the points (weight v_p:
    ``weights``, or volume/n each), K[(a,l),(b,m)] = Σ_p v_p (μ δ_ab Σ_c G_pcl G_pcm + μ G_pbl G_pam +
    λ G_pal G_pbm). This equals the Neo-Hookean Hessian at z = 0 (tested). M = I₃ ⊗ Σ_p v_p b_p b_pᵀ.

    Args:
        X: (n, 3) points; w: (n, H) weights; dw: (n, H, 3) their gradients (rigid column included).
        weights: (n,) integration weights (volumes); None: ``volume`` / n each.
        volumetric: "pointwise", or "projected": tr ε projected onto the weights' span in the λ term, as
            ``Simulator(volumetric="projected")`` does (:mod:`vid2sim.physics.volumetric`).
        trusted: the caller made X, w and dw (a training loop): their values are not checked, so nothing waits for
            the device.
    Returns:
        K, M: (3L, 3L) with L = 4H, differentiable in w and dw.
    """
    mu, lam = lame_parameters(1.0, poisson_ratio)
    K_mu, K_lam, M = subspace_stiffness_parts(X, w, dw, volume, weights, volumetric, trusted)
    return mu * K_mu + lam * K_lam, M


def subspace_stiffness_parts(X: Tensor, w: Tensor, dw: Tensor, volume: float, weights: Tensor | None = None,
                             volumetric: str = "pointwise", trusted: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """(K_μ, K_λ, M), each (3L, 3L): the subspace's stiffness at rest is μ K_μ + λ K_λ
    (:func:`subspace_stiffness_and_mass`, whose arguments these are)."""

    if volumetric not in ("pointwise", "projected"):
        raise ValueError(f"volumetric must be 'pointwise' or 'projected', got {volumetric!r}")
    n = X.shape[0]
    v = (float(volume) / n) if weights is None else weights[:, None]
    G = gradient_basis_unchecked(X, w, dw) if trusted else gradient_basis(X, w, dw)  # (n, 3, L)
    L = G.shape[2]
    Gf = G.reshape(n, 3 * L)
    Tp = Gf.T @ (Gf * v)  # [(a, l), (b, m)] = Σ_p v_p G_pal G_pbm
    T4 = Tp.reshape(3, L, 3, L)
    S = T4.diagonal(dim1=0, dim2=2).sum(-1)  # [l, m] = Σ_c T'[(c, l), (c, m)]
    eye3 = torch.eye(3, dtype=X.dtype, device=X.device)
    K_mu = torch.kron(eye3, S) + T4.permute(2, 1, 0, 3).reshape(3 * L, 3 * L)
    b = lbs_rows(X, w)
    M = torch.kron(eye3, b.T @ (b * v))
    if volumetric == "projected":  # Σ_pq v_p G_p P_pq G_q with the V-orthogonal projection P onto span(w)
        vv = v[:, 0] if torch.is_tensor(v) else torch.full((n,), v, dtype=X.dtype, device=X.device)
        WG = projection_basis(w, vv).T @ (Gf * vv[:, None])  # (H, 3L)
        return K_mu, WG.T @ WG, M
    return K_mu, Tp, M


def spanned_once(M: np.ndarray, *others: np.ndarray) -> tuple[np.ndarray, ...]:
    """M and ``others`` (each (m, m)) restricted to the directions the subspace spans once.

    A skinning subspace can span a direction twice: on a rod the handles w = z and w = z² give the LBS columns
    z·z and z²·1, which coincide. Its mass is then singular there, and its stiffness with it (the direction moves
    nothing), so the generalised eigenproblem is not defined; the Ritz values of the subspace are those of the
    pencil on M's range. The range is spanned by M's eigenvectors whose eigenvalue exceeds 1e-10 of the largest;
    when all do, the matrices are returned as they are.
    """
    lam, Q = np.linalg.eigh(0.5 * (M + M.T))
    keep = lam > 1e-10 * lam.max()
    if keep.all():
        return (M, *others)
    Q = Q[:, keep]
    return tuple(Q.T @ A @ Q for A in (M, *others))


def subspace_frequencies(field, points: Tensor, volumes: Tensor, youngs_modulus: float, poisson_ratio: float,
                         density: float, k: int = 6, volumetric: str = "pointwise",
                         mass_volumes: Tensor | None = None) -> np.ndarray:
    """The k lowest non-rigid Rayleigh–Ritz angular frequencies ω (rad/s) of the skinning subspace.

    Args:
        field: a :class:`~vid2sim.physics.SkinningField`.
        points: (n, 3) quadrature points (a simulator's cubature points ``sim.X``); volumes: (n,) their
            integration weights (``sim.vol``). Masses are ρ·volumes, as the simulator lumps them.
        volumetric: the simulator's volumetric term, "pointwise" or "projected".
        mass_volumes: (n,) the volumes the simulator lumps the mass on (``sim.mass_volumes``); None: ``volumes``.
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
        K, M = subspace_stiffness_and_mass(points, w, dw, 1.0, poisson_ratio, weights=volumes, volumetric=volumetric)
        if mass_volumes is not None:
            b = lbs_rows(points, w)
            M = torch.kron(torch.eye(3, dtype=b.dtype, device=b.device), b.T @ (b * mass_volumes[:, None]))
    Mn, Kn = spanned_once(M.double().cpu().numpy(), K.double().cpu().numpy())
    lam = eigh(Kn, Mn + 1e-14 * np.trace(Mn) / len(Mn) * np.eye(len(Mn)), eigvals_only=True)
    if len(lam) < k + 6:
        raise ValueError(f"the subspace has {len(lam)} degrees of freedom; k = {k} needs at least {k + 6}")
    return np.sqrt(np.clip(lam[6:6 + k], 0.0, None) * youngs_modulus / density)


def stiffness_calibration(field, points: Tensor, volumes: Tensor, vertices: Tensor | np.ndarray,
                          tets: Tensor | np.ndarray, poisson_ratio: float, volumetric: str = "pointwise",
                          mass_volumes: Tensor | None = None) -> float:
    """(ω_tets / ω_subspace)² of the lowest elastic mode: the factor ``Simulator(stiffness_scale=...)`` that makes
    the skinning subspace vibrate at the continuum's lowest frequency.

    A Rayleigh–Ritz subspace is stiffer than the continuum (its frequencies lie above), and a material fitted
    with it comes out soft by that factor. The continuum's frequency comes from quadratic tets
    (:func:`vid2sim.physics.tet_modes.tet_frequencies`) on a tet mesh of the same solid (``bench identify``: the
    FEM's rest mesh).

    Args:
        field: the skinning field; points: (K, 3) the simulator's cubature points (``sim.X``); volumes: (K,)
            their weights (``sim.vol``); vertices: (Nv, 3), tets: (Nt, 4) positively oriented, in the frame and
            units of ``points``; volumetric: the simulator's volumetric term ("pointwise" or "projected");
            mass_volumes: the volumes the simulator lumps its mass on (``sim.mass_volumes``; None: ``volumes``).
    Returns:
        s ∈ (0, ∞); it does not depend on E or ρ; s < 1 when the subspace is stiffer than the tets.
    """

    reference = tet_frequencies(vertices, tets, 1.0, poisson_ratio, 1.0, k=1, order=2)[0]
    reduced = subspace_frequencies(field, points, volumes, 1.0, poisson_ratio, 1.0, k=1, volumetric=volumetric,
                                   mass_volumes=mass_volumes)[0]
    if not (reference > 0 and reduced > 0):
        raise ValueError(f"the lowest elastic frequencies must be positive, got tets {reference}, subspace {reduced}")
    return float((reference / reduced) ** 2)


#: ν grid of :func:`stiffness_calibration_curve`: denser towards ½, where the subspace's locking grows fastest
CURVE_NUS = (0.0, 0.1, 0.2, 0.3, 0.35, 0.4, 0.43, 0.46, 0.48, 0.49)


#: modes the two-factor calibration matches, and the weight of the lowest one among them
TWO_FACTOR_MODES = 6
TWO_FACTOR_LOWEST_WEIGHT = 10.0
#: the two-factor fit's penalty on the curvature of log s and of log s_λ along u = −ln(1 − 2ν): on steps of
#: :data:`TWO_FACTOR_STEP` in u, a kink of 1 in either costs as much as the lowest mode off by 1 %
TWO_FACTOR_SMOOTHNESS = 0.1
#: the step in u of that penalty's unit (about :data:`CURVE_NUS`'s)
TWO_FACTOR_STEP = 0.4
#: its penalty on log s_λ − log s, which decides s_λ only where the modes do not (λ → 0 at ν → 0)
TWO_FACTOR_TIE = 0.01


def stiffness_calibration_curve(field, points: Tensor, volumes: Tensor, vertices: Tensor | np.ndarray | None,
                                tets: Tensor | np.ndarray | None, nus: tuple[float, ...] = CURVE_NUS, factors: int = 1,
                                reference: np.ndarray | None = None, volumetric: str = "pointwise",
                                mass_volumes: Tensor | None = None) -> StiffnessCurve:
    """The stiffness correction of the subspace at every ν of ``nus`` (``Simulator(stiffness_scale=curve)``).

    ``factors=1``: :func:`stiffness_calibration` at each ν, the factor s(ν) on the whole energy that makes the
    subspace's lowest frequency equal the continuum's.

    ``factors=2``: a factor s on μ and s_λ on λ at each ν, fitted (least squares in log frequency) to the
    :data:`TWO_FACTOR_MODES` lowest modes, the lowest weighted :data:`TWO_FACTOR_LOWEST_WEIGHT` × so that it
    stays matched (within ≈ 0.2 %). The subspace's volumetric locking sits in λ; one factor corrects it by
    softening shear as well, so the next modes fall up to 8 % below the continuum's and the impact's squash
    stays too stiff. With two factors s_λ comes out far below s (≈ 0.05 on soft-squashing shapes: the λ
    term of a few-handle subspace is mostly locking) and the six modes agree to a few percent.

    The tets' frequencies come from :func:`vid2sim.physics.tet_modes.tet_frequency_curve` (three sparse
    eigensolves for the whole grid, within 3e-4 of a direct solve per ν).

    With two factors the whole grid is one regularised fit (:func:`_two_factor_curve`). The six lowest modes are
    bending and twisting, and they barely involve λ below ν ≈ 0.4: many (s, s_λ) match them equally well (on a
    reconstruction's solid at ν = 0.3 the cost stayed within 2.4× for s_λ anywhere from 0.0025 to 7, with two
    local minima). Fitted ν by ν, the curve took whichever branch each fit met: separate fits per ν, even when
    each started from its neighbour's solution, gave s_λ = 135 at ν ≤ 0.1 (the bound's neighbourhood) and 25 at
    ν = 0.3 on one full-size benchmark solid, 6e-6 (the lower bound) at ν ≤ 0.2 on two others, and on a fourth a
    jump between ν = 0.43 and 0.46 from (s, s_λ) = (0.62, 1.38) to (0.49, 2.99). A model whose λ is 25 × too
    stiff at ν = 0.3 behaves as a nearly incompressible one, so a fit of ν inherits that arbitrariness, and
    between two grid values on different branches the interpolated factors match no mode (the lowest frequency
    7.8 % off there). One fit over the grid with small penalties on the curvature of log s and
    log s_λ along u = −ln(1 − 2ν) (:data:`TWO_FACTOR_SMOOTHNESS`; a power law in λ/μ, as the locking grows near
    ν = ½, is straight in u) and on log s_λ − log s (:data:`TWO_FACTOR_TIE`: where λ is not determined, at ν → 0,
    s_λ follows s) picks the smooth branch. On those four solids (full-preset benchmark scenes 8–11, their
    assets' fields and cubature) the largest lowest-mode error anywhere on [0, 0.49] (the interpolated curve
    against the tets' frequencies interpolated linearly in ν) is 0.03 / 0.17 / 0.19 / 0.06 % instead of 1.8 /
    7.8 / 0.38 / 0.06 %, the six modes' RMS log error at the grid values is the same or lower (0.75 / 1.83 /
    3.73 / 2.78 % against 0.80 / 2.26 / 3.69 / 2.79 %), s_λ stays within [0.009, 1.5], and both starts reach
    the same cost.

    Args: as :func:`stiffness_calibration`; ``nus`` the grid (strictly increasing, in [0, 0.5)); ``factors``
        1 or 2; ``reference``: the tets' frequencies at E = ρ = 1 already computed,
        ``tet_frequency_curve(vertices, tets, nus, k)`` with k = 1 (one factor) or :data:`TWO_FACTOR_MODES`
        (n, k); the mesh is then not needed; ``volumetric``: the simulator's volumetric term. With
        "projected" (:mod:`vid2sim.physics.volumetric`) the subspace does not lock and λ needs no factor of its
        own: use ``factors=1`` (two factors are refused; s_λ is then not determined by the modes at all);
        ``mass_volumes``: the volumes the simulator lumps its mass on (None: ``volumes``).
    Returns:
        a :class:`~vid2sim.physics.stiffness_curve.StiffnessCurve` (s, and s_λ with two factors, interpolated
        between the grid's ν).
    """

    if factors not in (1, 2) or isinstance(factors, bool):
        raise ValueError(f"factors must be 1 (one factor on E) or 2 (on mu and lambda), got {factors!r}")
    if factors == 2 and volumetric == "projected":
        raise ValueError("the projected volumetric term does not lock: calibrate it with factors=1 (one factor s(nu))")
    k = TWO_FACTOR_MODES if factors == 2 else 1
    if reference is None:
        if vertices is None or tets is None:
            raise ValueError(
                "stiffness_calibration_curve needs the tet mesh (vertices, tets) or its reference frequencies"
            )
        reference = tet_frequency_curve(vertices, tets, nus, k=k, order=2)
    reference = np.asarray(reference, dtype=float)
    if reference.shape != (len(nus), k):
        raise ValueError(
            f"the reference frequencies are {reference.shape}; {factors} factor(s) on {len(nus)} values of "
            f"nu need ({len(nus)}, {k})"
        )
    if factors == 2:
        return _two_factor_curve(field, points, volumes, reference, nus, mass_volumes)
    reference = reference[:, 0]
    scales = []
    for nu, ref in zip(nus, reference):
        reduced = subspace_frequencies(field, points, volumes, 1.0, float(nu), 1.0, k=1, volumetric=volumetric,
                                       mass_volumes=mass_volumes)[0]
        if not (ref > 0 and reduced > 0):
            raise ValueError(f"the lowest elastic frequencies must be positive at nu = {nu}, got tets {ref}, "
                             f"subspace {reduced}")
        scales.append(float((ref / reduced) ** 2))
    return StiffnessCurve(tuple(nus), tuple(scales))


def _curvature_rows(nus) -> np.ndarray:
    """(max(n − 2, 0), n): the second divided differences along u = −ln(1 − 2ν), times
    :data:`TWO_FACTOR_STEP` ², of values at the grid ``nus`` (n,).

    λ/μ = 2ν / (1 − 2ν), so a factor that follows a power of λ/μ near ν = ½ (the locking) is linear in u there and
    costs nothing; :data:`CURVE_NUS` is nearly uniform in u (steps 0.2–0.7)."""
    u = -np.log1p(-2.0 * np.asarray(nus, dtype=float))
    h = np.diff(u)
    rows = np.zeros((max(len(u) - 2, 0), len(u)))
    for i in range(1, len(u) - 1):
        scale = 2.0 * TWO_FACTOR_STEP ** 2 / (h[i - 1] + h[i])
        rows[i - 1, i - 1:i + 2] = scale * np.array([1.0 / h[i - 1], -1.0 / h[i - 1] - 1.0 / h[i], 1.0 / h[i]])
    return rows


def _two_factor_curve(field, points: Tensor, volumes: Tensor, reference: np.ndarray, nus,
                      mass_volumes: Tensor | None = None) -> StiffnessCurve:
    """:func:`stiffness_calibration_curve` with ``factors=2``; ``reference`` (n, k) the tets' frequencies.

    One regularised least-squares fit over the whole grid (module docstring of
    :func:`stiffness_calibration_curve`): x = (log s_1 … log s_n, log s_λ,1 … log s_λ,n), residuals
    ``w_j (log ω_ij(x) − log ω_ij^tets)`` (the lowest mode weighted :data:`TWO_FACTOR_LOWEST_WEIGHT`),
    :data:`TWO_FACTOR_SMOOTHNESS` × the curvature of log s and of log s_λ along u (:func:`_curvature_rows`), and
    :data:`TWO_FACTOR_TIE` × (log s_λ − log s). The Jacobian is exact (a Ritz value's derivative is its mode's
    Rayleigh quotient of the derivative of the stiffness). Two starts (s_λ = s, and s_λ = e⁻² s, both from the
    one-factor solution at every ν); the lower cost is kept.
    """
    from scipy.linalg import eigh
    from scipy.optimize import least_squares

    k = TWO_FACTOR_MODES
    with torch.no_grad():
        w, dw = field.weights_and_gradients(points)
        K_mu, K_lam, M = (m.double().cpu().numpy() for m in subspace_stiffness_parts(points, w, dw, 1.0, volumes))
        if mass_volumes is not None:
            b = lbs_rows(points, w)
            M = np.kron(np.eye(3), (b.T @ (b * mass_volumes[:, None])).double().cpu().numpy())
    M, K_mu, K_lam = spanned_once(M, K_mu, K_lam)
    M = M + 1e-14 * np.trace(M) / len(M) * np.eye(len(M))
    if len(M) < k + 6:
        raise ValueError(f"the subspace has {len(M)} degrees of freedom; the two-factor calibration needs {k + 6}")
    weights = np.array([TWO_FACTOR_LOWEST_WEIGHT] + [1.0] * (k - 1))
    n = len(nus)
    lame = [lame_parameters(1.0, float(nu)) for nu in nus]

    def ritz(i: int, log_s: float, log_lam: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ritz values ω² (k,) at the grid's i-th ν and their derivatives in log s and log s_λ (k,) each."""
        mu, lam = lame[i]
        A, B = math.exp(log_s) * mu * K_mu, math.exp(log_lam) * lam * K_lam
        values, vectors = eigh(A + B, M, subset_by_index=[6, 6 + k - 1])
        return (np.clip(values, 1e-300, None), np.einsum("aj,ab,bj->j", vectors, A, vectors),
                np.einsum("aj,ab,bj->j", vectors, B, vectors))

    one = []  # the one-factor solution: the lowest mode matched with s = s_λ
    for i, nu in enumerate(nus):
        if not (reference[i] > 0).all():
            raise ValueError(f"the tets' lowest elastic frequencies must be positive at nu = {nu}, got {reference[i]}")
        lowest = math.sqrt(ritz(i, 0.0, 0.0)[0][0])
        if not (reference[i, 0] / 20 < lowest < 20 * reference[i, 0]):  # e.g. a (near) zero-energy deformation mode
            raise ValueError(f"the subspace's lowest elastic frequency is {lowest:.3g} at nu = {nu}, against the "
                             f"tets' {reference[i, 0]:.3g}: a factor of {(reference[i, 0] / lowest) ** 2:.3g} would be "
                             "needed, so the subspace (or the tet mesh) is degenerate and its stiffness cannot be "
                             "calibrated")
        one.append(2.0 * math.log(reference[i, 0] / lowest))
    steps = _curvature_rows(nus)
    zeros = np.zeros_like(steps)
    regular = np.vstack([TWO_FACTOR_SMOOTHNESS * np.hstack([steps, zeros]),
                         TWO_FACTOR_SMOOTHNESS * np.hstack([zeros, steps]),
                         TWO_FACTOR_TIE * np.hstack([-np.eye(n), np.eye(n)])])  # linear in x

    def residuals_and_jacobian(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rows, jac = [], np.zeros((n * k, 2 * n))
        for i in range(n):
            values, d_s, d_lam = ritz(i, x[i], x[n + i])
            rows.append(weights * (0.5 * np.log(values) - np.log(reference[i])))
            jac[i * k:(i + 1) * k, i] = weights * d_s / (2.0 * values)
            jac[i * k:(i + 1) * k, n + i] = weights * d_lam / (2.0 * values)
        return np.concatenate(rows + [regular @ x]), np.vstack([jac, regular])

    cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def evaluate(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = residuals_and_jacobian(x)
        return cache[key]

    best = None
    for lift in (0.0, -2.0):
        x0 = np.clip(np.array(one + [v + lift for v in one]), -11.9, 11.9)
        fit = least_squares(lambda x: evaluate(x)[0], x0, jac=lambda x: evaluate(x)[1], bounds=(-12.0, 12.0))
        if best is None or fit.cost < best.cost:
            best = fit
    return StiffnessCurve(tuple(nus), tuple(float(math.exp(v)) for v in best.x[:n]),
                          tuple(float(math.exp(v)) for v in best.x[n:]))
