"""The study's figures: each map's sessions per group, the principal components, and a contact sheet of
every session's maps on one colour scale per map (``skinlayers.studies.study`` computes what they show)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from ..formats.files import atomic_write
from .study import MAPS, reconstructed

__all__ = ["SHEET_ROWS", "plot_study"]

#: Sessions per page of the contact sheet (a page stays readable at 110 dpi).
SHEET_ROWS = 24
#: Side of a map's thumbnail on the contact sheet (px of the map, box-averaged).
THUMB_PX = 64
#: Percentiles of the cohort's pixels that bound each map's colour scale.
COLOUR_PERCENTILES = (1, 99)


def plot_study(out: Path, rows: Sequence[dict], record: dict, maps: dict[str, Path]) -> dict[str, Path]:
    """Write ``study_groups.png`` (when the study has groups), ``study_pca.png`` (when it has components) and
    ``study_maps[_N].png`` (when a session has maps) into ``out``; their paths by kind."""
    done = reconstructed(rows)
    for stale in [*out.glob("study_maps*.png"), out / "study_groups.png", out / "study_pca.png"]:
        stale.unlink(missing_ok=True)  # an earlier run's figures would pass for this one's
    paths: dict[str, Path] = {}
    if record["groups"]:
        paths["groups"] = _save(_groups_figure(done, list(record["groups"])), out / "study_groups.png")
    if record["principal_components"]["explained"]:
        paths["pca"] = _save(_pca_figure(done, record), out / "study_pca.png")
    names = [r["session"] for r in done if r["session"] in maps]
    pages = [names[i:i + SHEET_ROWS] for i in range(0, len(names), SHEET_ROWS)]
    limits = _colour_limits(names, maps) if names else {}
    for k, page in enumerate(pages):
        suffix = "" if len(pages) == 1 else f"_{k + 1}"
        paths[f"maps{suffix}"] = _save(_sheet_figure(page, maps, limits), out / f"study_maps{suffix}.png")
    return paths


def _groups_figure(rows: Sequence[dict], columns: list[str]):
    """One row per grouping column, one panel per map: the sessions' trimmed means by group."""
    fig, axes = plt.subplots(len(columns), len(MAPS), figsize=(3.0 * len(MAPS), 2.8 * len(columns)), squeeze=False)
    for i, column in enumerate(columns):
        values = sorted({str(r[column]) for r in rows})
        for j, name in enumerate(MAPS):
            data = [[float(r[f"{name}_trimmed_mean"]) for r in rows if str(r[column]) == v] for v in values]
            ax = axes[i, j]
            ax.boxplot(data, showfliers=False)
            for k, d in enumerate(data):
                ax.plot(np.full(len(d), k + 1.0), d, "o", ms=3, alpha=0.6)
            ax.set_xticks(range(1, len(values) + 1), values, rotation=30, fontsize=7)
            ax.set_title(f"{name} by {column}", fontsize=9)
    fig.suptitle("each session's trimmed mean over its scored pixels")
    fig.tight_layout()
    return fig


def _pca_figure(rows: Sequence[dict], record: dict):
    """The sessions on the first two components (one if only one), and each component's loadings."""
    pca = record["principal_components"]
    scores = np.array([pca["scores"][str(r["session"])] for r in rows])
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    second = scores[:, 1] if scores.shape[1] > 1 else np.zeros(len(scores))
    left.scatter(scores[:, 0], second, s=14)
    for r, x, y in zip(rows, scores[:, 0], second):
        left.annotate(str(r["session"]), (x, y), fontsize=6, alpha=0.7)
    left.set_xlabel(f"PC1 ({100 * pca['explained'][0]:.0f}% of the variance)")
    left.set_ylabel(f"PC2 ({100 * pca['explained'][1]:.0f}%)" if len(pca["explained"]) > 1 else "")
    loadings = np.array(pca["loadings"])
    image = right.imshow(loadings, cmap="RdBu_r", vmin=-1, vmax=1)
    right.set_xticks(range(len(pca["maps"])), pca["maps"])
    right.set_yticks(range(len(loadings)), [f"PC{k + 1}" for k in range(len(loadings))])
    fig.colorbar(image, ax=right, label="loading")
    fig.suptitle("principal components of the sessions' standardised trimmed means")
    fig.tight_layout()
    return fig


def _colour_limits(names: list[str], maps: dict[str, Path]) -> dict[str, tuple[float, float]]:
    """Per map, the cohort's percentiles (over every session's thumbnail) that bound its colour scale."""
    pixels = {name: [] for name in MAPS}
    for session in names:
        for name, thumb in _thumbnails(maps[session]).items():
            pixels[name].append(thumb[np.isfinite(thumb)])
    joined = {name: np.concatenate(v) if v else np.empty(0) for name, v in pixels.items()}
    return {name: tuple(np.percentile(v, COLOUR_PERCENTILES)) if v.size else (0.0, 1.0) for name, v in joined.items()}


def _sheet_figure(names: list[str], maps: dict[str, Path], limits: dict[str, tuple[float, float]]):
    """One row per session, one column per map, every row on the cohort's colour scales."""
    fig, axes = plt.subplots(len(names), len(MAPS), figsize=(1.7 * len(MAPS), 1.6 * len(names) + 0.4), squeeze=False)
    for i, session in enumerate(names):
        thumbs = _thumbnails(maps[session])
        for j, name in enumerate(MAPS):
            ax = axes[i, j]
            ax.imshow(thumbs[name], cmap="magma", vmin=limits[name][0], vmax=limits[name][1])
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(name, fontsize=9)
            if j == 0:
                ax.set_ylabel(session, fontsize=6, rotation=0, ha="right", va="center")
    fig.tight_layout()
    return fig


def _thumbnails(path: Path) -> dict[str, np.ndarray]:
    """Each map of a maps file box-averaged to at most ``THUMB_PX`` a side."""
    from ..formats.exr import read_exr  # noqa: PLC0415

    channels, _ = read_exr(path)
    out = {}
    for name in MAPS:
        image = np.asarray(channels[name], dtype=np.float64)
        k = max(1, int(np.ceil(max(image.shape) / THUMB_PX)))
        h, w = image.shape[0] // k * k, image.shape[1] // k * k
        out[name] = image[:h, :w].reshape(h // k, k, w // k, k).mean(axis=(1, 3))
    return out


def _save(fig, path: Path) -> Path:
    """The figure as PNG at ``path`` (atomically)."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    return atomic_write(path, buffer.getvalue())
