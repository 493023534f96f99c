"""A coupling flow conditioned on a keypoint pair: the invertible network of the learned map.

In normalised coordinates u (see :mod:`kpflow.maps.learned`), with ``a = u(A(S))`` the aligned source keypoints and
``b = u(T)`` the targets (both ``[N, D]``), the flow is ``G(u | a, b) = L_K o ... o L_1(u)`` with K affine couplings
(Dinh et al. 2017, Eqs. 4-5) behind fixed rotations Q_k (random orthogonal, det +1, so every layer couples a
different split of directions). Layer k sees the keypoints where the layers before it have carried them,
``p^k = L_{k-1} o ... o L_1(a)``, rotated: ``P = p^k Q_k^T``, ``B = b Q_k^T``; for a point ``v = Q_k u = (v_I, v_J)``

    k(v_I, P_i) = exp(-|v_I - P_{i,I}|^2 / (2 l_k^2)),     tau = alpha_k (K + mu_k I)^-1 (B_J - P_J),  K_ij = k(P_i, P_j),
    h = tanh(W_2 tanh(W_1 v_I + P_k c + b_1) + b_2),       [s~, t~] = W_3 h + b_3   (coupling_depth 2;
                                                           depth 1: h = tanh(W_1 v_I + P_k c + b_1)),
    s = g_k * s_max * tanh(s~ / s_max),
    t = g_k * t~ + sum_i k(v_I, P_i) tau_i,
    L_k(u) = Q_k^T (v_I, v_J * exp(s) + t).

The kernel term is kernel ridge regression of the keypoints' remaining residual along the moved directions on
their kept coordinates: it moves keypoint i by about ``alpha_k`` times its residual (exactly, as ``mu -> 0``) and
decays to zero away from the keypoints; the MLP term corrects it. The scene's condition is computed once per pair:

    c = E([a, b - a])                               (a tanh MLP on the flattened pair),
    (l_k, alpha_k, mu_k) = heads(c),                l, mu > 0, alpha in (0, 1),
    g = tanh(W_g tanh(V (b - a)))                   (bias-free, so g = 0 when b = a).

Properties by construction: each layer inverts in closed form, ``v_J = (v'_J - t) * exp(-s)`` (t and s depend on
v_I only); the Jacobian determinant is ``prod exp(s) > 0`` everywhere; and when the alignment already explains the
pair (``b = a``, in particular ``S = T``) every gate and every residual is 0 and G is the identity. The MLPs' last
layers start at zero.

normflows' conditional couplings are its rational-quadratic splines, measured an order of magnitude beyond the
learned map's time budget on a CPU, hence this small affine coupling with the scene's part of every layer computed
once per scene.
"""

from __future__ import annotations

import torch
from torch import nn

from kpflow.maps.validation import scale_floor


def normalise(
    aligned_source: torch.Tensor, target: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The normalised coordinates of a pair: ``a = n(A S + t)``, ``b = n(T)`` with ``n(y) = (y - m) / sigma``,
    ``m, sigma`` the targets' mean and RMS spread (:mod:`kpflow.maps.learned`). Returns ``(a, b, m, sigma)`` for
    pairs ``[B, N, D]`` (``m [B, 1, D]``, ``sigma [B, 1, 1]``)."""
    m = target.mean(-2, keepdim=True)
    sigma = (target - m).square().sum(-1).mean(-1).sqrt()[:, None, None].clamp_min(scale_floor(target))
    return (aligned_source - m) / sigma, (target - m) / sigma, m, sigma


def _mlp(d_in: int, hidden: int, d_out: int, depth: int, bias: bool = True) -> nn.Sequential:
    mods: list[nn.Module] = []
    width = d_in
    for _ in range(depth):
        mods += [nn.Linear(width, hidden, bias=bias), nn.Tanh()]
        width = hidden
    return nn.Sequential(*mods, nn.Linear(width, d_out, bias=bias))


def rotations(n: int, dim: int, seed: int) -> torch.Tensor:
    """``n`` random rotations ``[n, dim, dim]`` (orthogonal, det +1) from ``seed``, computed in float64."""
    g = torch.Generator().manual_seed(seed)
    q = torch.linalg.qr(torch.randn(n, dim, dim, generator=g, dtype=torch.float64)).Q
    q[:, :, 0] *= torch.linalg.det(q).sign()[:, None]
    return q


class ConditionalFlow(nn.Module):
    """G(u | a, b) of the module docstring for ``n_keypoints`` keypoints in ``dim`` dimensions.

    Usage: ``cond = flow.condition(a, b)`` once per batch of pairs ``[B, N, D]``; then ``flow(u, cond)``,
    ``flow.inverse(v, cond)`` and ``flow.log_det(u, cond)`` for points ``u [B, M, D]``.
    """

    def __init__(
        self,
        n_keypoints: int,
        dim: int = 2,
        n_layers: int = 16,
        hidden: int = 64,
        context: int = 128,
        encoder_depth: int = 2,
        s_max: float = 2.0,
        seed: int = 0,
        coupling_depth: int = 1,
    ) -> None:
        super().__init__()
        if dim < 2:
            raise ValueError(f"a coupling flow needs dim >= 2, got {dim}")
        if coupling_depth not in (1, 2):
            raise ValueError(
                f"coupling_depth must be 1 or 2 (hidden layers of each coupling's MLP), got {coupling_depth}"
            )
        self.coupling_depth = coupling_depth
        self.n_keypoints, self.dim, self.n_layers, self.hidden, self.s_max = n_keypoints, dim, n_layers, hidden, s_max
        self.n_keep = dim // 2
        self.n_move = dim - self.n_keep
        self.seed = seed
        self.register_buffer("rotations", rotations(n_layers, dim, seed).float(), persistent=False)
        self.encoder = _mlp(2 * n_keypoints * dim, context, context, encoder_depth)
        self.gate = _mlp(n_keypoints * dim, context, n_layers, 1, bias=False)
        self.heads = nn.Linear(context, 3 * n_layers)  # per layer: the kernel's width, step and ridge
        nn.init.zeros_(self.heads.weight)
        with torch.no_grad():
            self.heads.bias.copy_(torch.tensor([-1.0, 2.0, -6.0]).repeat(n_layers))  # l 0.31, alpha 0.88, mu 0.0025
        self.w1 = nn.ModuleList(nn.Linear(self.n_keep, hidden) for _ in range(n_layers))
        self.p1 = nn.Linear(context, n_layers * hidden, bias=False)
        self.w2 = nn.ModuleList(nn.Linear(hidden, hidden) for _ in range(n_layers if coupling_depth == 2 else 0))
        self.w3 = nn.ModuleList(nn.Linear(hidden, 2 * self.n_move) for _ in range(n_layers))
        for last in self.w3:
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)

    def _apply(self, fn, recurse: bool = True):
        """Casts and moves rebuild the rotations from the seed, so they stay orthogonal to the new precision (a
        float32 rotation cast to float64 is not orthogonal to float64 precision, and Q^T would not invert it)."""
        out = super()._apply(fn, recurse)
        like = self.w1[0].weight
        self.rotations = rotations(self.n_layers, self.dim, self.seed).to(device=like.device, dtype=like.dtype)
        return out

    def encode(self, a: torch.Tensor, b: torch.Tensor) -> dict[str, torch.Tensor]:
        """The encoder's outputs for pairs ``a, b [B, N, D]``: the first layer's scene part ``pc [B, K, hidden]``
        and, each ``[B, K]``, the gates, the kernel widths, steps and ridges."""
        if a.shape[-2:] != (self.n_keypoints, self.dim) or b.shape != a.shape:
            raise ValueError(
                f"this learned map was trained on {self.n_keypoints} keypoints in {self.dim}-D; got source {tuple(a.shape)} "
                f"and target {tuple(b.shape)}"
            )
        r = (b - a).flatten(1)
        c = self.encoder(torch.cat([a.flatten(1), r], -1))
        heads = self.heads(c).reshape(-1, self.n_layers, 3)
        return {
            "pc": self.p1(c).reshape(-1, self.n_layers, self.hidden),
            "gates": torch.tanh(self.gate(r)),
            "width": nn.functional.softplus(heads[..., 0]) + 1e-3,
            "step": torch.sigmoid(heads[..., 1]),
            "ridge": nn.functional.softplus(heads[..., 2]) + 1e-3,
        }

    def condition(self, a: torch.Tensor, b: torch.Tensor) -> dict:
        """Everything about the scene the layers need, for pairs ``a, b [B, N, D]``: :meth:`encode`'s outputs and
        per layer the keypoints' kept coordinates in its rotated frame (``points``, ``K x [B, N, n_keep]``) and the
        kernel term's values tau (``values``, ``K x [B, N, n_move]``)."""
        cond = self.encode(a, b)
        eye = torch.eye(self.n_keypoints, dtype=a.dtype, device=a.device)
        cond["points"], cond["values"] = [], []
        p = a
        for k in range(self.n_layers):
            q = self.rotations[k]
            v = p @ q.T
            keep = v[..., : self.n_keep]
            cond["points"].append(keep)
            gram = self._kernel(keep, keep, cond["width"][:, k]) + cond["ridge"][:, k, None, None] * eye
            residual = (b @ q.T - v)[..., self.n_keep :]
            cond["values"].append(cond["step"][:, k, None, None] * torch.linalg.solve(gram, residual))
            p = self._layer(k, p, cond)[0]
        return cond

    @staticmethod
    def _kernel(x: torch.Tensor, y: torch.Tensor, width: torch.Tensor) -> torch.Tensor:
        """exp(-|x_m - y_n|^2 / (2 width^2)) ``[B, M, N]`` for ``x [B, M, d]``, ``y [B, N, d]``, ``width [B]``."""
        return torch.exp(-(x[:, :, None, :] - y[:, None]).square().sum(-1) / (2 * width[:, None, None].square()))

    def _params(self, k: int, keep: torch.Tensor, cond) -> tuple[torch.Tensor, torch.Tensor]:
        """Log-scale s and shift t ``[B, M, n_move]`` of layer ``k`` at kept coordinates ``keep [B, M, n_keep]``."""
        h = torch.tanh(self.w1[k](keep) + cond["pc"][:, k, None])
        st = self.w3[k](torch.tanh(self.w2[k](h)) if self.coupling_depth == 2 else h)
        g = cond["gates"][:, k, None, None]
        s = g * self.s_max * torch.tanh(st[..., : self.n_move] / self.s_max)
        kernel = self._kernel(keep, cond["points"][k], cond["width"][:, k])  # [B, M, N]
        return s, g * st[..., self.n_move :] + kernel @ cond["values"][k]

    def _layer(self, k: int, u: torch.Tensor, cond) -> tuple[torch.Tensor, torch.Tensor]:
        q = self.rotations[k]
        v = u @ q.T
        keep, move = v[..., : self.n_keep], v[..., self.n_keep :]
        s, t = self._params(k, keep, cond)
        return torch.cat([keep, move * torch.exp(s) + t], -1) @ q, s.sum(-1)

    def forward(self, u: torch.Tensor, cond) -> torch.Tensor:
        """G(u | cond) for ``u [B, M, D]``."""
        return self._run(u, cond)[0]

    def log_det(self, u: torch.Tensor, cond) -> torch.Tensor:
        """log det dG/du ``[B, M]`` (the sum of the layers' s; the rotations have det 1)."""
        return self._run(u, cond)[1]

    def _run(self, u: torch.Tensor, cond) -> tuple[torch.Tensor, torch.Tensor]:
        logdet = torch.zeros(u.shape[:-1], dtype=u.dtype, device=u.device)
        for k in range(self.n_layers):
            u, ld = self._layer(k, u, cond)
            logdet = logdet + ld
        return u, logdet

    def inverse(self, y: torch.Tensor, cond) -> torch.Tensor:
        """G^-1(y | cond) for ``y [B, M, D]``, layer by layer in closed form."""
        for k in reversed(range(self.n_layers)):
            q = self.rotations[k]
            v = y @ q.T
            keep, move = v[..., : self.n_keep], v[..., self.n_keep :]
            s, t = self._params(k, keep, cond)
            y = torch.cat([keep, (move - t) * torch.exp(-s)], -1) @ q
        return y
