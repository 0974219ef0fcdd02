"""How compliant the body is where it hits something: quadratic tets against the skinning subspace.

A skinning subspace of a few handles cannot represent the local indentation under a contact patch: under the
same impact load its compliance is 0.6–0.9 × the continuum's on the benchmark's objects, even after the
stiffness calibration of :mod:`vid2sim.physics.modes` has matched the lowest vibration frequency. The reduced
model then bounces off the floor too stiffly, and a fit compensates with a wrong ν.

The load is a set of contact forces F_i on the body (the floor's, in a state of a simulation that touches it),
applied quasi-statically to the free body with inertia relief: the rigid-body part of the load is balanced by the
d'Alembert force of the acceleration it causes, and the compliance is C = fᵀu of the elastic response u (at
E = 1). Both models get the same nodal forces; their ratio does not depend on E.

:func:`contact_layer_calibration` turns the compliance the subspace is missing into the depth h of the
simulator's contact layer (:class:`~vid2sim.physics.solver.Simulator`, ``contact_layer``): each barrier acts
in series with a layer of stiffness 2 k_b per unit area, k_b = E·s / ((1 − ν²) h), which adds the compliance
(1 − ν²) h / (2 E s) Σ_i |F_i|² / a_i for contact areas a_i. A negative value (the calibrated subspace is
already the softer one under that load) is reported and the layer clamped to 0.
:func:`contact_layer_from_simulation` sums this over the floor loads of a simulation's states; the patches
depend on the layer, so it is iterated to a fixed point (``vid2sim bench identify --calibrate-contact``).

Measured on two ``bench identify`` scenes, the layer this gives makes the contact too soft: both fits got worse
(loss 2.4× and 9× higher; docs/architecture.md, "The layer measured per object does not work"). The static
compliance is mostly smooth deformation that the subspace already has and a short impact does not excite.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import Tensor

from vid2sim.physics.external import Floor
from vid2sim.physics.modes import subspace_stiffness_and_mass
from vid2sim.physics.reduced import lbs_rows
from vid2sim.physics.sparse_lu import SymmetricLU, nested_dissection
from vid2sim.physics.tet_modes import rigid_modes, tet_stiffness_and_mass


def _relieve(force: np.ndarray, mass: np.ndarray, rigid: np.ndarray) -> np.ndarray:
    """The load minus the d'Alembert force of the rigid acceleration it causes: orthogonal to ``rigid``."""
    acceleration = np.linalg.solve(rigid.T @ (mass @ rigid), rigid.T @ force)
    return force - mass @ (rigid @ acceleration)


class TetCompliance:
    """The free quadratic-tet body's quasi-static response to loads, with inertia relief (E = 1, ρ = 1).

    Factorises the stiffness once (a statically determinate 3-2-1 support removes the rigid modes; a relieved
    load needs no reaction there), so several loads at one ν cost one solve each.

    Args:
        vertices: (Nv, 3) rest positions; tets: (Nt, 4) positively oriented.
        poisson_ratio: ν.
    Attributes:
        nodes: (N, 3) the quadratic mesh's nodes (the vertices, then one midpoint per edge:
            :func:`vid2sim.physics.tet_modes.quadratic_tet_nodes`).
    """

    def __init__(self, vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray, poisson_ratio: float) -> None:
        K, self._M, self.nodes = tet_stiffness_and_mass(vertices, tets, 1.0, poisson_ratio, 1.0, order=2)
        nodes = self.nodes
        self._rigid = rigid_modes(nodes)
        a = int(np.argmin(nodes[:, 0]))
        b = int(np.argmax(np.linalg.norm(nodes - nodes[a], axis=1)))
        ab = nodes[b] - nodes[a]
        c = int(np.argmax(np.linalg.norm(np.cross(nodes - nodes[a], ab), axis=1)))
        normal = np.cross(ab, nodes[c] - nodes[a])
        across = np.argsort(np.abs(ab))[:2]  # b moves along ab's main axis only
        fixed = [3 * a, 3 * a + 1, 3 * a + 2, *(3 * b + across), 3 * c + int(np.argmax(np.abs(normal)))]
        self._free = np.setdiff1d(np.arange(3 * len(nodes)), fixed)
        # The full stiffness's nested-dissection order, restricted to the free degrees of freedom.
        position = np.full(3 * len(nodes), -1)
        position[self._free] = np.arange(len(self._free))
        order = position[nested_dissection(K)]
        self._lu = SymmetricLU(K[self._free][:, self._free], order[order >= 0])

    def displacement(self, node_forces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(u, f): the elastic displacement (N, 3) under ``node_forces`` (N, 3) and the relieved load (N, 3)."""
        if node_forces.shape != self.nodes.shape:
            raise ValueError(f"node_forces must have shape {self.nodes.shape} (one per quadratic-tet node), "
                             f"got {node_forces.shape}")
        f = _relieve(node_forces.reshape(-1).astype(np.float64), self._M, self._rigid)
        u = np.zeros_like(f)
        u[self._free] = self._lu.solve(f[self._free])
        return u.reshape(-1, 3), f.reshape(-1, 3)

    def compliance(self, node_forces: np.ndarray) -> float:
        """C = fᵀu of the relieved load f and its displacement u."""
        u, f = self.displacement(node_forces)
        return float((f * u).sum())


def tet_impact_compliance(vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray, node_forces: np.ndarray,
                          poisson_ratio: float) -> float:
    """C = fᵀu (E = 1, ρ = 1) of the free quadratic-tet body under nodal forces (N, 3) on the quadratic mesh's
    nodes (rest frame), with inertia relief (:class:`TetCompliance`)."""
    return TetCompliance(vertices, tets, poisson_ratio).compliance(node_forces)


def subspace_impact_compliance(field, cubature_points: Tensor, cubature_weights: Tensor, load_points: Tensor,
                               forces: np.ndarray, poisson_ratio: float) -> float:
    """C = fᵀu (E = 1, ρ = 1) of the skinning subspace under forces at points, with inertia relief.

    Args:
        field: the :class:`~vid2sim.physics.SkinningField`.
        cubature_points: (K, 3) and cubature_weights: (K,) — the simulator's quadrature (``sim.X``, ``sim.vol``).
        load_points: (P, 3) rest positions where the forces act; forces: (P, 3), in the rest frame.
    """
    with torch.no_grad():
        w, dw = field.weights_and_gradients(cubature_points)
        K, M = subspace_stiffness_and_mass(cubature_points, w, dw, 1.0, poisson_ratio, weights=cubature_weights)
        b = lbs_rows(load_points, field(load_points)).double().cpu().numpy()  # (P, L)
    K, M = K.double().cpu().numpy(), M.double().cpu().numpy()
    f = np.einsum("pa,pl->al", forces, b).reshape(-1)  # the (3, L) row-major layout of y
    values, vectors = np.linalg.eigh(K)
    rigid = vectors[:, :6]  # the subspace holds the rigid motions exactly: K's six zero modes
    f = _relieve(f, M, rigid)
    u = np.linalg.lstsq(K, f, rcond=1e-10)[0]
    return float(f @ u)


@dataclass
class ContactCalibration:
    """The contact layer that gives the calibrated subspace the continuum's impact compliance.

    Attributes:
        layer: h (m) for ``Simulator(contact_layer=)``: ``raw_layer`` clamped to ≥ 0.
        raw_layer: the unclamped value (negative: the calibrated subspace is the softer one).
        poisson_ratio: the ν it was measured at; stiffness_scale: s at that ν.
        tet_compliance, subspace_compliance: C at E = 1 (the subspace's without s).
        compliance_ratio: s·C_tet / C_sub — how much too stiff the calibrated subspace is under the load.
    """

    layer: float
    raw_layer: float
    poisson_ratio: float
    stiffness_scale: float
    tet_compliance: float
    subspace_compliance: float
    compliance_ratio: float

    def to_dict(self) -> dict:
        return asdict(self)


def contact_layer_calibration(field, cubature_points: Tensor, cubature_weights: Tensor,
                              vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray, load_nodes: np.ndarray,
                              forces: np.ndarray, areas: np.ndarray, poisson_ratio: float,
                              stiffness_scale: float = 1.0, tet: TetCompliance | None = None) -> ContactCalibration:
    """The contact layer h that makes the subspace (scaled by s) as compliant as quadratic tets under a load.

    Args:
        field, cubature_points, cubature_weights: the reduced model (see :func:`subspace_impact_compliance`).
        vertices, tets: the object's rest tet mesh (see :func:`tet_impact_compliance`).
        load_nodes: (P,) indices of the loaded quadratic-tet nodes; forces: (P, 3) their forces (rest frame);
            areas: (P,) their contact areas (the barrier weights, m²).
        poisson_ratio: ν; stiffness_scale: the simulator's s at that ν.
        tet: a :class:`TetCompliance` of the same mesh and ν, to reuse its factorisation.
    Returns:
        :class:`ContactCalibration`.
    """
    forces = np.asarray(forces, dtype=np.float64)
    areas = np.asarray(areas, dtype=np.float64)
    load_nodes = np.asarray(load_nodes)
    if forces.ndim != 2 or forces.shape[1] != 3 or len(forces) == 0 or forces.shape[:1] != load_nodes.shape \
            or areas.shape != load_nodes.shape:
        raise ValueError(f"need load_nodes (P,), forces (P, 3) and areas (P,) with P >= 1, got "
                         f"{load_nodes.shape}, {forces.shape}, {areas.shape}")
    if not np.all(areas > 0):
        raise ValueError("contact areas must be positive")
    if not stiffness_scale > 0:
        raise ValueError(f"stiffness_scale must be > 0, got {stiffness_scale}")
    tet = tet if tet is not None else TetCompliance(vertices, tets, poisson_ratio)
    nodes = tet.nodes
    node_forces = np.zeros_like(nodes)
    np.add.at(node_forces, load_nodes, forces)
    c_tet = tet.compliance(node_forces)
    points = torch.as_tensor(nodes[load_nodes], dtype=cubature_points.dtype, device=cubature_points.device)
    c_sub = subspace_impact_compliance(field, cubature_points, cubature_weights, points, forces, poisson_ratio)
    per_area = float(((forces ** 2).sum(1) / areas).sum())
    raw = 2.0 * (stiffness_scale * c_tet - c_sub) / ((1.0 - poisson_ratio ** 2) * per_area)
    return ContactCalibration(max(raw, 0.0), raw, float(poisson_ratio), float(stiffness_scale), c_tet, c_sub,
                              stiffness_scale * c_tet / c_sub)


def simulated_contact_loads(sim, states) -> list[tuple[np.ndarray, np.ndarray]]:
    """The floor's forces on the contact points in each state of a simulation, in the rest frame.

    Args:
        sim: the :class:`~vid2sim.physics.solver.Simulator` (its floor barrier, contact layer, contact points).
        states: its :class:`~vid2sim.physics.solver.SimState` s.
    Returns:
        per state with contact: (indices (P,) of the touching contact points, forces (P, 3)).
    """

    floors = [e for e in sim.externals if isinstance(e, Floor)]
    if len(floors) != 1 or sim.contact_points is None:
        raise ValueError("simulated_contact_loads needs one Floor and the simulator's contact_points")
    floor = floors[0]
    with torch.no_grad():
        k_b = sim.contact_layer_stiffness()
        kappa = floor.stiffness if k_b is None else floor.stiffness / (1.0 + floor.stiffness / float(k_b))
        X = sim.X.double()
        Xh = torch.cat([X, torch.ones_like(X[:, :1])], 1)
        weights = sim.contact_weights.double().cpu().numpy()
        out = []
        for state in states:
            z = state.z.detach().double()
            depth = (floor.height - sim.positions(sim.contact_points.double(), z)[:, 2]).cpu().numpy()
            touching = np.flatnonzero(depth > 0)
            if len(touching) == 0:
                continue
            affine = torch.linalg.lstsq(Xh, sim.positions(X, z)).solution[:3].T.cpu().numpy()
            U, _, Vt = np.linalg.svd(affine)
            up = (U @ Vt).T @ np.array([0.0, 0.0, 1.0])  # the floor normal in the rest frame
            magnitude = 2.0 * kappa * weights[touching] * depth[touching]
            out.append((touching, magnitude[:, None] * up[None]))
    return out


def contact_layer_from_simulation(sim, states, tet: TetCompliance, contact_nodes: np.ndarray,
                                  poisson_ratio: float, stiffness_scale: float) -> ContactCalibration:
    """The contact layer that matches the continuum's compliance under the floor loads of a simulation.

    Every state in contact contributes its load; the loads keep their magnitudes, so the hardest impacts
    weigh most: h = 2 Σ_k (s C_tet,k − C_sub,k) / ((1 − ν²) Σ_k Σ_i |F_ki|² / a_i). Run it on a simulation
    with the layer it returns to make the patches consistent with it (the layer spreads them).

    Args:
        sim, states: the simulator and a simulation of it (:func:`simulated_contact_loads`).
        tet: the object's continuum at ``poisson_ratio`` (:class:`TetCompliance`).
        contact_nodes: (Nc,) the quadratic-tet node of each of ``sim.contact_points``.
        poisson_ratio, stiffness_scale: ν and the simulator's s at ν.
    """
    loads = simulated_contact_loads(sim, states)
    if not loads:
        raise ValueError("the simulation never touches the floor: no contact load to calibrate the layer with")
    contact_nodes = np.asarray(contact_nodes)
    areas = sim.contact_weights.double().cpu().numpy()
    c_tet = c_sub = per_area = 0.0
    for touching, forces in loads:
        node_forces = np.zeros_like(tet.nodes)
        np.add.at(node_forces, contact_nodes[touching], forces)
        c_tet += tet.compliance(node_forces)
        c_sub += subspace_impact_compliance(sim.field, sim.X, sim.vol, sim.contact_points[touching].double(),
                                            forces, poisson_ratio)
        per_area += float(((forces ** 2).sum(1) / areas[touching]).sum())
    raw = 2.0 * (stiffness_scale * c_tet - c_sub) / ((1.0 - poisson_ratio ** 2) * per_area)
    return ContactCalibration(max(raw, 0.0), raw, float(poisson_ratio), float(stiffness_scale), c_tet, c_sub,
                              stiffness_scale * c_tet / c_sub)
