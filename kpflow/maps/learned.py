"""Learned map: one forward pass of a trained conditional flow instead of a fit per scene.

For a keypoint pair ``(S, T)`` the map is

    phi(x) = R(n^-1(G(n(A x + t) | a, b))),   n(y) = (y - m) / sigma,   a = n(A S + t),  b = n(T),

with ``A x + t`` the rigid (or other) alignment fitted on the pair, ``m, sigma`` the targets' mean and RMS spread,
G the :class:`~kpflow.maps.conditional_flow.ConditionalFlow` trained by :class:`~kpflow.maps.map_module.MapModule`
to carry ``a`` onto ``b`` (``train.py experiment=pusht_map``), and R an optional refinement: ``refine_steps`` ILWR
steps fitted on the remaining residual ``(n^-1(G(a)), T)``, itself exactly invertible (the identity when
``refine_steps=0``). "Fitting" a scene is the alignment plus one pass of the flow's encoder.

Every part is invertible in closed form (or, for R, solved to tolerance), det J > 0 wherever the alignment is a
rotation (G's determinant is a product of exponentials), and phi is the alignment itself when the alignment explains
the pair (G's gates vanish; in particular phi = id when S = T). Batched over scenes like ``ILWRMap``.

Use it from configuration as ``map=learned map.checkpoint=PATH`` (a ``MapModule`` checkpoint, read with
``weights_only``; each checkpoint is read once per process and dtype).
"""

from __future__ import annotations

import functools
import os
import stat
from typing import Callable

import torch

from kpflow.maps import learned_kernels
from kpflow.maps.affine import AlignedMap
from kpflow.maps.base import TransportMap
from kpflow.maps.conditional_flow import ConditionalFlow, normalise
from kpflow.maps.ilwr import ILWRMap


@functools.lru_cache(maxsize=8)
def _load(path: str, mtime_ns: int, dtype: torch.dtype, device: str) -> tuple[ConditionalFlow, str]:
    from kpflow.maps.map_module import MapModule
    from kpflow.utils.checkpoint import UnsafeCheckpointError, load_checkpoint

    try:
        module = load_checkpoint(MapModule, path)
    except UnsafeCheckpointError:
        raise
    except ValueError as e:  # it read, but not as a learned map (another model's checkpoint, a damaged file)
        raise ValueError(
            f"{e}; a learned map needs a MapModule checkpoint (python train.py experiment=pusht_map)"
        ) from e
    flow = module.flow.to(device=device, dtype=dtype).eval().requires_grad_(False)
    return flow, str(module.hparams.alignment)


def load_flow(
    path: str | os.PathLike, dtype: torch.dtype = torch.float64, device: str | torch.device = "cpu"
) -> tuple[ConditionalFlow, str]:
    """The trained flow of a :class:`~kpflow.maps.map_module.MapModule` checkpoint (frozen, in ``dtype`` on ``device``)
    and the alignment it was trained behind. Cached per file (re-read when the file changes), dtype and device.

    Raises ``FileNotFoundError`` when nothing is at ``path`` and ``ValueError`` naming ``path`` when it is not a
    learned map's checkpoint (or :class:`~kpflow.utils.checkpoint.UnsafeCheckpointError`, when it could run code)."""
    p = os.path.abspath(path)
    try:
        st = os.stat(p)
    except OSError:
        st = None
    if st is None or not stat.S_ISREG(st.st_mode):
        raise FileNotFoundError(
            f"no learned-map checkpoint at {path} (train one: python train.py experiment=pusht_map)"
        )
    return _load(p, st.st_mtime_ns, dtype, str(torch.device(device)))


def check_map_factory(make_map: Callable[[], TransportMap], n_keypoints: int, dim: int, use: str) -> None:
    """Build one map from the factory ``make_map`` now, while the run is being built, so that a map that cannot work
    fails before its first fit: a learned map reads its checkpoint (a missing file, or one that is not a learned
    map's, raises naming it; :func:`load_flow`) and must have been trained on keypoint sets of ``n_keypoints``
    ``dim``-D points, which ``use`` (said in the error) fits it on; otherwise ``ValueError`` names the checkpoint
    and both layouts."""
    made = make_map()
    if isinstance(made, LearnedMap) and (made.n_keypoints, made.dim) != (n_keypoints, dim):
        raise ValueError(
            f"the learned map {made.checkpoint or '(in memory)'} was trained on {made.n_keypoints} keypoints in "
            f"{made.dim}-D, but {use} fits it on {n_keypoints} keypoints in {dim}-D: pass a learned map trained on those"
        )


class LearnedMap(AlignedMap):
    """The learned map of the module docstring.

    Args:
        checkpoint: a ``MapModule`` checkpoint (``outputs/<task>_map/<run>/checkpoints/last.ckpt``).
        refine_steps: ILWR steps on the flow's residual (0: none).
        flow: an in-memory flow instead of a checkpoint (tests); then ``alignment`` says which. Its weights are
            read into the compiled path once, at the first fit: do not train it further while maps use it.
        compiled: run float64 CPU queries through the fused loops of :mod:`~kpflow.maps.learned_kernels` (the
            torch layers otherwise, and always for queries that need gradients, e.g. :meth:`jacobian`).
    """

    supports_batch = True

    def __init__(
        self,
        checkpoint: str | os.PathLike | None = None,
        refine_steps: int = 0,
        flow: ConditionalFlow | None = None,
        alignment: str = "rigid",
        compiled: bool = True,
    ) -> None:
        if (checkpoint is None) == (flow is None):
            raise ValueError("LearnedMap needs exactly one of checkpoint (a MapModule checkpoint) or flow")
        loaded = (
            load_flow(checkpoint) if checkpoint is not None else None
        )  # fail here, with the path, not at the first fit
        super().__init__(alignment if loaded is None else loaded[1] if loaded[1] != "none" else None)
        if int(refine_steps) < 0:
            raise ValueError(f"refine_steps must be >= 0, got {refine_steps}")
        self.checkpoint, self.refine_steps, self._given_flow, self.compiled = (
            checkpoint,
            int(refine_steps),
            flow,
            compiled,
        )
        self._loaded = {(torch.float64, "cpu"): loaded[0]} if loaded is not None else {}
        trained = flow if flow is not None else loaded[0]
        self.n_keypoints, self.dim = int(trained.n_keypoints), int(trained.dim)  #: the keypoint sets it was trained on
        self.flow: ConditionalFlow | None = None
        self.refiner: ILWRMap | None = None
        self._cond = None  # the torch condition, built on first need
        self._packed = None  # the compiled path's (weights, condition), when it applies

    def _flow_for(self, dtype: torch.dtype, device: torch.device | str = "cpu") -> ConditionalFlow:
        if self._given_flow is not None:
            return self._given_flow.to(device=device, dtype=dtype)
        key = (dtype, str(torch.device(device)))
        if key not in self._loaded:
            self._loaded[key] = load_flow(self.checkpoint, dtype, device)[0]
        return self._loaded[key]

    def _fit(self, source: torch.Tensor, target: torch.Tensor) -> None:
        flow = self._flow_for(source.dtype, source.device)
        if source.shape[-2:] != (flow.n_keypoints, flow.dim):
            raise ValueError(
                f"this learned map was trained on {flow.n_keypoints} keypoints in {flow.dim}-D; got {source.shape[-2]} "
                f"keypoints in {source.shape[-1]}-D"
            )
        self.flow = flow
        needs_grad = torch.is_grad_enabled() and (source.requires_grad or target.requires_grad)
        fast = self.compiled and source.dtype == torch.float64 and source.device.type == "cpu" and not needs_grad
        if not (fast and self._fit_alignment_compiled(source, target)):
            self._fit_alignment(source, target)
        self._a, self._b, self.centre, self.spread = normalise(self.alignment._forward(source), target)
        self._cond = None
        self._packed = self._compile(flow, self._a, self._b) if fast else None
        self.refiner = None
        if self.refine_steps:
            self.refiner = ILWRMap(n_steps=self.refine_steps, alignment="none").fit(self._net_forward(source), target)

    @staticmethod
    def _compile(flow: ConditionalFlow, a: torch.Tensor, b: torch.Tensor) -> tuple:
        weights = getattr(flow, "_packed_weights", None)
        if weights is None:
            weights = flow._packed_weights = learned_kernels.pack(flow)
        with torch.no_grad():
            enc = {k: v.numpy() for k, v in flow.encode(a, b).items()}
        pts, vals = learned_kernels.condition_layers(
            a.detach().numpy(),
            b.detach().numpy(),
            *weights,
            enc["pc"],
            enc["gates"],
            enc["width"],
            enc["step"],
            enc["ridge"],
            flow.s_max,
        )
        return weights, (enc["pc"], enc["gates"], enc["width"], pts, vals, flow.s_max)

    @property
    def cond(self) -> dict:
        """The torch layers' condition of the fitted pairs (:meth:`ConditionalFlow.condition`)."""
        if self._cond is None:
            self._cond = self.flow.condition(self._a, self._b)
        return self._cond

    def _flow(self, u: torch.Tensor, inverse: bool = False) -> torch.Tensor:
        if self._packed is not None and not (torch.is_grad_enabled() and u.requires_grad):
            weights, cond = self._packed
            out, _ = learned_kernels.transport(u.detach().numpy(), inverse, *weights, *cond)
            return torch.from_numpy(out)
        return self.flow.inverse(u, self.cond) if inverse else self.flow(u, self.cond)

    def _net_forward(self, x: torch.Tensor) -> torch.Tensor:
        u = (self.alignment._forward(x) - self.centre) / self.spread
        return self._flow(u) * self.spread + self.centre

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self._net_forward(x)
        return y if self.refiner is None else self.refiner._forward(y)

    def _inverse(self, y: torch.Tensor) -> torch.Tensor:
        if self.refiner is not None:
            y = self.refiner._inverse(y)
        u = self._flow((y - self.centre) / self.spread, inverse=True)
        return self.alignment._inverse(u * self.spread + self.centre)

    def log_det_jacobian(self, x) -> torch.Tensor:
        """log |det J(x)| ``[...]``: the flow's own log-determinant plus the alignment's (and the refinement's)."""
        flat, shape = self._flatten(x)
        u = (self.alignment._forward(flat) - self.centre) / self.spread
        total = self.flow.log_det(u, self.cond) + torch.linalg.slogdet(self.alignment.A).logabsdet[:, None]
        if self.refiner is not None:
            total = total + torch.linalg.slogdet(self.refiner._jacobian(self._net_forward(flat))).logabsdet
        return total.reshape(shape[:-1])
