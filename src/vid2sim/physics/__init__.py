"""Mesh-free reduced-order simulation: skinning field, materials, external energies, implicit Euler, adjoint, Neural Jacobian."""
