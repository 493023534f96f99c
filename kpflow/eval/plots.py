"""Matplotlib drawings shared by the experiments: frames, trajectories with uncertainty bands, vector fields."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402


def draw_frame(ax, position: torch.Tensor, rotation: torch.Tensor, size: float, label: str | None = None) -> None:
    """A 2-D frame as a red x axis and a green y axis from its origin."""
    p, r = position.detach().cpu().numpy(), rotation.detach().cpu().numpy()
    ax.arrow(*p, *(size * r[:, 0]), color="tab:red", width=size * 0.06, length_includes_head=True, zorder=5)
    ax.arrow(*p, *(size * r[:, 1]), color="tab:green", width=size * 0.06, length_includes_head=True, zorder=5)
    if label:
        ax.annotate(label, p, textcoords="offset points", xytext=(4, -10), fontsize=7)


def draw_band(ax, mean: torch.Tensor, std: torch.Tensor, k: float = 2.0, **kwargs) -> None:
    """Shade the k-sigma tube around a 2-D curve: offsets of k * |std| along the curve's normals."""
    m = mean.detach().cpu().numpy()
    s = k * std.detach().cpu().norm(dim=-1).numpy() / np.sqrt(std.shape[-1])
    tangent = np.gradient(m, axis=0)
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True).clip(1e-12)
    upper, lower = m + s[:, None] * normal, m - s[:, None] * normal
    poly = np.concatenate([upper, lower[::-1]])
    ax.fill(poly[:, 0], poly[:, 1], alpha=kwargs.pop("alpha", 0.25), lw=0, **kwargs)


def draw_curve(ax, xy: torch.Tensor, **kwargs) -> None:
    a = xy.detach().cpu().numpy()
    ax.plot(a[:, 0], a[:, 1], **kwargs)


def draw_field(ax, field, lo: np.ndarray, hi: np.ndarray, n: int = 25, dtype=torch.float64) -> None:
    """Stream lines of a 2-D vector field ``field(x [M, 2]) -> [M, 2]`` over the box [lo, hi]."""
    xs, ys = np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n)
    gx, gy = np.meshgrid(xs, ys)
    pts = torch.as_tensor(np.stack([gx.ravel(), gy.ravel()], -1), dtype=dtype)
    v = field(pts).detach().cpu().numpy()
    speed = np.linalg.norm(v, axis=-1).reshape(gx.shape)
    ax.streamplot(
        xs,
        ys,
        v[:, 0].reshape(gx.shape),
        v[:, 1].reshape(gx.shape),
        color=speed,
        cmap="Greys",
        density=0.9,
        linewidth=0.6,
        arrowsize=0.6,
    )


def new_figure(rows: int, cols: int, size: float = 3.2):
    fig, axes = plt.subplots(rows, cols, figsize=(size * cols, size * rows), squeeze=False)
    for ax in axes.flat:
        ax.set_aspect("equal")
        ax.tick_params(labelsize=6)
    return fig, axes


def close(fig) -> None:
    plt.close(fig)


def draw_matches(
    ax, image_a: np.ndarray, image_b: np.ndarray, pixels_a, pixels_b, good, title: str = "", dropped=None
) -> None:
    """Two images side by side with a line per matched pair ``pixels_a [n, 2]`` -> ``pixels_b [n, 2]`` (x, y),
    green where ``good [n]`` and red elsewhere, dashed where ``dropped [n]``."""
    width = image_a.shape[1]
    dropped = np.zeros(len(good), bool) if dropped is None else np.asarray(dropped)
    ax.imshow(np.concatenate([image_a, image_b], axis=1))
    for (xa, ya), (xb, yb), ok, out in zip(np.asarray(pixels_a), np.asarray(pixels_b), np.asarray(good), dropped):
        colour = "lime" if ok else "red"
        ax.plot([xa, xb + width], [ya, yb], "--" if out else "-", color=colour, lw=1)
        ax.scatter([xa, xb + width], [ya, yb], color=colour, s=10)
    ax.set_axis_off()
    ax.set_title(title, fontsize=7)


def offline_figure(
    path: Path,
    recorded: np.ndarray,
    steps: list[int],
    predicted: list[np.ndarray],
    episode: int,
    names: Sequence[str] | None = None,
    dims: Sequence[int] | None = None,
) -> Path:
    """One held-out episode's recorded actions (a panel per action dimension, at most 4) and each predicted chunk
    drawn from the step it was asked at, cut at the episode's last step (the offline check,
    :mod:`kpflow.eval.offline`).

    ``names``: one per action dimension (the panels' titles; default ``action dim i``); ``dims``: the
    dimensions drawn (default the first 4)."""
    length, width = recorded.shape
    names = [f"action dim {d}" for d in range(width)] if names is None else list(names)
    if len(names) != width:
        raise ValueError(f"{len(names)} names for actions of {width} values: {names}")
    dims = list(range(min(width, 4)) if dims is None else dims)
    fig, axes = plt.subplots(1, len(dims), figsize=(3.6 * len(dims), 3.2), squeeze=False)
    for d, ax in zip(dims, axes.flat):
        ax.plot(recorded[:, d], color="black", lw=1.5, label="recorded")
        for i, (t, chunk) in enumerate(zip(steps, predicted)):
            shown = chunk[: max(length - t, 0)]  # a chunk asked near the end runs past it: drawn up to the last step
            ax.plot(range(t, t + len(shown)), shown[:, d], color="tab:orange", lw=1,
                    label="predicted chunks" if i == 0 else None)  # fmt: skip
        ax.set_xlim(0, max(length - 1, 1))
        ax.set_title(names[d], fontsize=11)
        ax.set_xlabel("step in the episode", fontsize=10)
        ax.set_ylabel("action value", fontsize=10)
        ax.tick_params(labelsize=9)
        ax.grid(alpha=0.3)
    fig.suptitle(f"held-out episode {episode}: recorded and predicted actions", fontsize=12)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=9, frameon=False, bbox_to_anchor=(0.5, -0.02))
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.savefig(path, dpi=100, bbox_inches="tight")
    close(fig)
    return Path(path)
