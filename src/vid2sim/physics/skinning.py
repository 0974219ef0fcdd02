"""Neural skinning field, linear blend skinning (LBS) and the deformation gradient in closed form.

Paper §3 ("Mesh-Free, Reduced-Order Simulation", after Simplicits): a small MLP maps a rest position
X ∈ R³ to skinning weights w(X) ∈ R^H. H = learned handles + 1 constant "rigid" handle whose weight is
identically 1 (always the LAST column). Each handle j carries a 3×4 displacement affine Z_j and

    x(X) = X + Σ_j w_j(X) Z_j [X; 1]                              (LBS, z = 0 is the rest state)
    F(X) = ∂x/∂X = I + Σ_j Z_j ( [I; 0] w_j(X) + [X; 1] ∇w_j(X)ᵀ )

Layouts used everywhere in vid2sim:

- reduced state z ∈ R^{12H}, handle-major, each Z_j row-major: ``z[12*j + 4*a + k] = Z_j[a, k]``;
- F flattened row-major: ``F.reshape(N, 9)``, index ``3*a + c`` for ``F[a, c]``;
- the compact gradient basis ``G: (N, 3, 4H)`` with ``G[p, c, 4j+k] = w_j δ_kc + Xh_k ∂_c w_j`` (Xh = [X, 1],
  δ_3c = 0), so that ``F[a, c] = δ_ac + Σ_{j,k} Z_j[a, k] G[p, c, 4j+k]``: row a of F depends only on
  row a of each Z_j.

∇_X w is computed in closed form by pushing the Jacobian forward through the layers (forward-mode, plain
torch ops), so it is exact, cheap and differentiable with respect to the network parameters.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.nn import functional as Fn

from vid2sim.physics.input_frame import InputFrame, check_points, uniform_


def _check_weights(X: Tensor, w: Tensor) -> int:
    check_points(X)
    if w.ndim != 2 or w.shape[0] != X.shape[0] or w.shape[1] < 1:
        raise ValueError(f"w must have shape (N, H) = ({X.shape[0]}, H) with H >= 1, got {tuple(w.shape)}")
    if not bool(torch.isfinite(w).all()):
        raise ValueError("skinning weights w contain NaN or infinite values")
    return w.shape[1]


def _check_z(z: Tensor, num_handles_total: int, allow_batch: bool = False) -> None:
    n = 12 * num_handles_total
    ok = (z.ndim == 1 and z.shape[0] == n) or (allow_batch and z.ndim == 2 and z.shape[1] == n)
    if not ok:
        want = f"({n},)" + (f" or (B, {n})" if allow_batch else "")
        raise ValueError(
            f"z must have shape {want} for H = {num_handles_total} handles (12 numbers each), got {tuple(z.shape)}"
        )
    if not bool(torch.isfinite(z).all()):
        raise ValueError("z contains NaN or infinite values")


def homogeneous(X: Tensor) -> Tensor:
    """Xh = [X, 1]: (N, 4) for X: (N, 3)."""
    return torch.cat([X, torch.ones_like(X[:, :1])], dim=1)


class SkinningField(InputFrame):
    """Neural skinning weights w(X) = [MLP(X), 1] (paper §3 and supplementary "LBS and Jacobian Network").

    Architecture: Linear(3, width) + ELU, ``hidden_layers`` × [Linear(width, width) + ELU],
    Linear(width, num_handles). With the defaults (10 handles, width 64) the last layer holds
    640 weights + 10 biases = 650 numbers — the part the Stage I hypernetwork predicts.

    Args:
        num_handles: learned handles (the constant rigid handle is added on top).
        width: hidden width.
        hidden_layers: number of width×width hidden layers.
        seed: if given, the initialisation is deterministic (drawn from a private generator) — this is the
            "template network" whose hidden layers stay at their seeded init while Stage I predicts the
            last layer. ``None`` draws from the global torch RNG.

    Initialisation (see :meth:`reset_parameters`): He/Kaiming-uniform hidden layers and a small output
    layer. PyTorch's default ``nn.Linear`` init shrinks the signal by ≈ 1/√3 per layer, so after 9 ELU
    layers the last hidden features over the unit box are numerically rank ≈ 4 (normalised singular values
    1.2, 6e-3, 5e-3, 4e-3, then < 4e-4): 10 orthogonal weight functions are then out of reach for a
    last-layer-only fit and data-free training stalls at the W = 0 saddle of the orthogonality loss
    (orthogonality MSE still 0.07 after 1500 iterations at the paper's settings). With this init the features
    keep O(1) singular values and the same training reaches 5e-4 by 1500 iterations.
    """

    #: scale of the output layer's initial weights relative to U(−1/√fan_in, 1/√fan_in); biases start at 0
    output_init_scale: float = 0.01

    def __init__(self, num_handles: int = 10, width: int = 64, hidden_layers: int = 8, seed: int | None = None) -> None:
        super().__init__()
        for name, v, lo in (("num_handles", num_handles, 1), ("width", width, 1), ("hidden_layers", hidden_layers, 0)):
            if not isinstance(v, int) or isinstance(v, bool) or v < lo:
                raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
        self.num_handles = num_handles
        self.width = width
        self.hidden_layers = hidden_layers
        dims = [3] + [width] * (hidden_layers + 1) + [num_handles]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self._init_input_frame()  # MLP((X − input_centre) / input_scale); identity unless set
        self.reset_parameters(seed)

    @torch.no_grad()
    def reset_parameters(self, seed: int | None = None) -> None:
        """Re-draw all parameters (deterministic for a given seed).

        Input and hidden layers: weights U(±√(6/fan_in)) (Kaiming-uniform, gain √2), biases U(±1/√fan_in).
        Output layer: weights U(±s/√fan_in) with s = ``output_init_scale`` (0.01), biases 0, so training starts
        from small weights instead of Gram matrices ~10⁴× too large.
        """
        gen = None
        if seed is not None:
            gen = torch.Generator(device="cpu")
            gen.manual_seed(int(seed))

        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            fan_in = layer.in_features
            if i < last:
                uniform_(layer.weight, math.sqrt(6.0 / fan_in), gen)
                uniform_(layer.bias, 1.0 / math.sqrt(fan_in), gen)
            else:
                uniform_(layer.weight, self.output_init_scale / math.sqrt(fan_in), gen)
                layer.bias.zero_()

    # ---- sizes ---------------------------------------------------------------------------------
    @property
    def num_handles_total(self) -> int:
        """H = learned handles + 1 rigid handle."""
        return self.num_handles + 1

    @property
    def last_layer_size(self) -> int:
        """Numbers in the last layer: num_handles × width weights + num_handles biases (650 by default)."""
        return self.num_handles * self.width + self.num_handles

    @property
    def last_layer(self) -> nn.Linear:
        """The output layer (the one Stage I predicts and ``last_layer_only`` training updates)."""
        return self.layers[-1]  # type: ignore[return-value]

    def get_last_layer(self) -> Tensor:
        """(last_layer_size,) copy: weight row-major (num_handles × width), then bias (num_handles)."""
        layer = self.last_layer
        return torch.cat([layer.weight.detach().reshape(-1), layer.bias.detach().reshape(-1)]).clone()

    @torch.no_grad()
    def set_last_layer(self, vec: Tensor) -> None:
        """Load the last layer from ``vec: (last_layer_size,)`` (layout of :meth:`get_last_layer`)."""
        if not isinstance(vec, Tensor):
            vec = torch.as_tensor(vec)
        if vec.ndim != 1 or vec.shape[0] != self.last_layer_size:
            raise ValueError(
                f"last-layer vector must have shape ({self.last_layer_size},) = {self.num_handles}×{self.width} "
                f"weights + {self.num_handles} biases, got {tuple(vec.shape)}"
            )
        if not bool(torch.isfinite(vec).all()):
            raise ValueError("last-layer vector contains NaN or infinite values")
        layer = self.last_layer
        nw = self.num_handles * self.width
        layer.weight.copy_(vec[:nw].reshape(self.num_handles, self.width).to(layer.weight))
        layer.bias.copy_(vec[nw:].to(layer.bias))

    # ---- evaluation ----------------------------------------------------------------------------
    def learned_weights(self, X: Tensor) -> Tensor:
        """MLP output only (no rigid column): (N, num_handles) for X: (N, 3); evaluated in the parameters' dtype
        and returned in X's (a float64 simulator reads a float32 field)."""
        h = self._canonical(self._in_parameters_dtype(X, self.last_layer.weight))
        for layer in self.layers[:-1]:
            h = Fn.elu(layer(h))
        return self.layers[-1](h).to(X.dtype)

    def forward(self, X: Tensor) -> Tensor:
        """Skinning weights w: (N, H) for rest positions X: (N, 3); ``w[:, -1] == 1`` (rigid handle)."""
        w = self.learned_weights(X)
        return torch.cat([w, torch.ones_like(w[:, :1])], dim=1)

    def weights_and_gradients(self, X: Tensor) -> tuple[Tensor, Tensor]:
        """Weights and their spatial gradients in closed form.

        Forward-mode propagation of ∂h/∂X through every layer: a Linear layer maps (h, Dh) to (W h + b, W Dh),
        ELU maps them to (elu(h), elu'(h) ⊙ Dh) with elu'(u) = 1 for u > 0 and e^u otherwise. Exact,
        vectorised, and differentiable with respect to the parameters.

        Args:
            X: (N, 3) rest positions (of any floating dtype: evaluated in the parameters' and returned in X's).
        Returns:
            w: (N, H) weights (last column ≡ 1); dw: (N, H, 3) with ``dw[p, j, c] = ∂w_j/∂X_c`` (rigid column 0).
        """
        w, dw = self._weights_and_gradients(self._in_parameters_dtype(X, self.last_layer.weight))
        return w.to(X.dtype), dw.to(X.dtype)

    def _weights_and_gradients(self, X: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`weights_and_gradients` without checking X (for callers that did, e.g. a training loop)."""
        n = X.shape[0]
        h = self._canonical(X)
        # D: (N, 3, d) — Jacobian transposed so that Linear is a right-multiplication by Wᵀ.
        D = (torch.eye(3, dtype=X.dtype, device=X.device) / self.input_scale).expand(n, 3, 3)
        for layer in self.layers[:-1]:
            u = layer(h)
            D = D @ layer.weight.T
            h = Fn.elu(u)
            slope = h.clamp_max(0.0) + 1.0  # elu'(u) = 1 for u > 0 (h > 0), e^u = elu(u) + 1 for u <= 0
            D = D * slope.unsqueeze(1)
        last = self.last_layer
        w = last(h)
        dw = (D @ last.weight.T).transpose(1, 2)  # (N, num_handles, 3)
        w = torch.cat([w, torch.ones_like(w[:, :1])], dim=1)
        dw = torch.cat([dw, torch.zeros_like(dw[:, :1])], dim=1)
        return w, dw


# ---- LBS and deformation gradient ------------------------------------------------------------------

def lbs_matrix(X: Tensor, w: Tensor) -> Tensor:
    """Dense LBS matrix B: (N, 3, 12H) with ``x_p = X_p + B_p @ z`` for X: (N, 3), w: (N, H).

    ``B[p, a, 12j + 4a' + k] = δ_aa' w_j(X_p) Xh_k``. Memory grows as N·36H; use :func:`deform` to move points.
    """
    H = _check_weights(X, w)
    n = X.shape[0]
    b = w[:, :, None] * homogeneous(X)[:, None, :]  # (N, H, 4)
    eye = torch.eye(3, dtype=X.dtype, device=X.device)
    return torch.einsum("pjk,ab->pajbk", b, eye).reshape(n, 3, 12 * H)


def deform(X: Tensor, w: Tensor, z: Tensor) -> Tensor:
    """Deformed positions x: (N, 3) = X + Σ_j w_j Z_j [X; 1] for X: (N, 3), w: (N, H), z: (12H,), in X's dtype
    (a float64 simulator's state moves float32 points)."""
    H = _check_weights(X, w)
    _check_z(z, H)
    b = (w[:, :, None] * homogeneous(X)[:, None, :]).reshape(X.shape[0], 4 * H)  # (N, 4H), index 4j+k
    Zt = z.to(X.dtype).reshape(H, 3, 4).transpose(1, 2).reshape(4 * H, 3)  # Zt[4j+k, a] = Z_j[a, k]
    return X + b @ Zt


def gradient_basis(X: Tensor, w: Tensor, dw: Tensor) -> Tensor:
    """Compact deformation-gradient basis G: (N, 3, 4H).

    ``G[p, c, 4j+k] = w_j(X_p) δ_kc + Xh_k ∂_c w_j(X_p)`` (Xh = [X, 1], δ_3c = 0), so that
    ``F[a, c] = δ_ac + Σ_{j,k} Z_j[a, k] G[p, c, 4j+k]``.

    Args:
        X: (N, 3) rest positions; w: (N, H) weights; dw: (N, H, 3) spatial gradients of w.
    """
    H = _check_weights(X, w)
    n = X.shape[0]
    if dw.shape != (n, H, 3):
        raise ValueError(f"dw must have shape (N, H, 3) = ({n}, {H}, 3), got {tuple(dw.shape)}")
    if not bool(torch.isfinite(dw).all()):
        raise ValueError("weight gradients dw contain NaN or infinite values")
    return gradient_basis_unchecked(X, w, dw)


def gradient_basis_unchecked(X: Tensor, w: Tensor, dw: Tensor) -> Tensor:
    """:func:`gradient_basis` without checking its inputs."""
    n, H = w.shape
    delta = torch.eye(3, 4, dtype=X.dtype, device=X.device)  # delta[c, k] = δ_kc, zero for k = 3
    G = (
        w[:, None, :, None] * delta[None, :, None, :]
        + dw.transpose(1, 2)[:, :, :, None] * homogeneous(X)[:, None, None, :]
    )
    return G.reshape(n, 3, 4 * H)


def _check_basis(G: Tensor) -> int:
    if G.ndim != 3 or G.shape[1] != 3 or G.shape[2] % 4 != 0 or G.shape[2] == 0:
        raise ValueError(f"G must have shape (N, 3, 4H), got {tuple(G.shape)}")
    return G.shape[2] // 4


def deformation_gradient(G: Tensor, z: Tensor) -> Tensor:
    """F: (N, 3, 3) from the basis G: (N, 3, 4H) and z: (12H,), in G's dtype.

    A batch of states z: (B, 12H) is also accepted and gives F: (B, N, 3, 3).
    """
    H = _check_basis(G)
    _check_z(z, H, allow_batch=True)
    return deformation_gradient_unchecked(G, z)


def deformation_gradient_unchecked(G: Tensor, z: Tensor) -> Tensor:
    """:func:`deformation_gradient` without checking its inputs."""
    H = G.shape[2] // 4
    eye = torch.eye(3, dtype=G.dtype, device=G.device)
    z = z.to(G.dtype)
    Y = z.reshape(*z.shape[:-1], H, 3, 4).transpose(-3, -2).reshape(*z.shape[:-1], 3, 4 * H)  # Y[a, 4j+k]
    if z.ndim == 1:
        return eye + torch.einsum("al,pcl->pac", Y, G)
    return eye + torch.einsum("bal,pcl->bpac", Y, G)


def dF_dz(G: Tensor) -> Tensor:
    """Dense Jacobian J: (N, 9, 12H) with ``F.reshape(N, 9) = I.flatten() + J @ z`` for G: (N, 3, 4H).

    ``J[p, 3a + c, 12j + 4a' + k] = δ_aa' G[p, c, 4j + k]`` — block structured; only 1/3 of it is non-zero.
    """
    H = _check_basis(G)
    n = G.shape[0]
    eye = torch.eye(3, dtype=G.dtype, device=G.device)
    return torch.einsum("pcjk,ab->pacjbk", G.reshape(n, 3, H, 4), eye).reshape(n, 9, 12 * H)
