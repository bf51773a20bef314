"""The stability matrix's heat maps (``skinlayers.analyses.stability``): one PNG per method, a row per condition, a
cell per strength, coloured by how far the cell is from its worst target (1: at the target) and marked
met, told (a warning naming the condition), told, not why (a warning naming another cause) or SILENT
(a target missed and nothing said)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

__all__ = ["CellTargets", "draw_heat_maps", "worst_ratio"]

#: Colour scale of the worst ratio (log): green below the target, red beyond.
RATIO_RANGE = (0.1, 10.0)


@dataclass(frozen=True)
class CellTargets:
    """What a cell is held to (the stability matrix's ``TARGETS``, ``RESIDUAL_AT_NOISE``, ``SIGMA_COVER``) and
    whether its warnings name its condition (``names_cause``): given by the matrix, so the charts need not
    import it."""

    maps: dict[str, float]
    residual_at_noise: float
    sigma_cover: float
    names_cause: Callable[[dict], bool]


def worst_ratio(row: dict, targets: CellTargets) -> float:
    """The cell's largest ratio to a target: each map's error over its target, the residual over its
    limit, the σ coverage wanted over the coverage had, on the scored pixels and on the hair-flagged ones
    (1: exactly at the worst target)."""
    try:
        ratios = [float(row[f"error_{m}"]) / t for m, t in targets.maps.items()]
        ratios.append(float(row["residual_over_noise"]) / targets.residual_at_noise)
        ratios.append(targets.sigma_cover / max(float(row["sigma_cover"]), 1e-3))
        flagged = float(row.get("sigma_cover_flagged") or "nan")
        if math.isfinite(flagged):
            ratios.append(targets.sigma_cover / max(flagged, 1e-3))
    except (TypeError, ValueError, KeyError):
        return math.nan  # a refused cell has no maps
    return max(ratios)


def draw_heat_maps(rows: list[dict], plan, out: Path, targets: CellTargets) -> list[Path]:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415
    from matplotlib.colors import LogNorm  # noqa: PLC0415

    from .sweep import cell_text  # noqa: PLC0415

    paths = []
    conditions = ["clean", *plan.conditions]
    width = max(len(s) for s in plan.conditions.values()) if plan.conditions else 1
    for method in plan.methods:
        grid = [[math.nan] * width for _ in conditions]
        fig, ax = plt.subplots(figsize=(1.3 * width + 3.5, 0.42 * len(conditions) + 1.4))
        for i, name in enumerate(conditions):
            strengths = [""] if name == "clean" else list(plan.conditions[name])
            for j, s in enumerate(strengths):
                row = next((r for r in rows if r["method"] == method and r["condition"] == name and str(r["strength"]) == cell_text(s)), None)
                if row is None:
                    continue
                grid[i][j] = worst_ratio(row, targets)
                met, told = str(row["meets_targets"]) == "True", str(row["detected"]) == "True"
                mark = "met" if met else ("told" if told and targets.names_cause(row) else "told, not why" if told else "SILENT")
                ax.text(j, i, f"{s}\n{mark}" if s != "" else mark, ha="center", va="center", fontsize=7,
                        fontweight="bold" if mark == "SILENT" else "normal")
        image = ax.imshow(grid, cmap="RdYlGn_r", norm=LogNorm(*RATIO_RANGE), aspect="auto")
        ax.set_yticks(range(len(conditions)), conditions, fontsize=8)
        ax.set_xticks(range(width), [str(j + 1) for j in range(width)], fontsize=8)
        ax.set_xlabel("strength (in the sweep's order; the value is in the cell)")
        ax.set_title(f"{method}: worst ratio to a target per cell (met · told · told, not why · SILENT)", fontsize=9)
        fig.colorbar(image, ax=ax, label="worst ratio to a target")
        fig.tight_layout()
        path = out / f"stability_{method}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths
