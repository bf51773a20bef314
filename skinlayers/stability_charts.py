"""The stability matrix's heat maps (``skinlayers.stability``): one PNG per method, a row per condition, a
cell per strength, coloured by how far the cell is from its worst target (1: at the target) and marked
met, told (a warning naming the condition), told, not why (a warning naming another cause) or SILENT
(a target missed and nothing said)."""

from __future__ import annotations

import math
from pathlib import Path

__all__ = ["draw_heat_maps", "worst_ratio"]

#: Colour scale of the worst ratio (log): green below the target, red beyond.
RATIO_RANGE = (0.1, 10.0)


def worst_ratio(row: dict) -> float:
    """The cell's largest ratio to a target: each map's error over its target, the residual over its
    limit, the σ coverage wanted over the coverage had, on the scored pixels and on the hair-flagged ones
    (1: exactly at the worst target)."""
    from .stability import RESIDUAL_AT_NOISE, SIGMA_COVER, TARGETS  # noqa: PLC0415

    try:
        ratios = [float(row[f"error_{m}"]) / t for m, t in TARGETS.items()]
        ratios.append(float(row["residual_over_noise"]) / RESIDUAL_AT_NOISE)
        ratios.append(SIGMA_COVER / max(float(row["sigma_cover"]), 1e-3))
        flagged = float(row.get("sigma_cover_flagged") or "nan")
        if math.isfinite(flagged):
            ratios.append(SIGMA_COVER / max(flagged, 1e-3))
    except (TypeError, ValueError, KeyError):
        return math.nan  # a refused cell has no maps
    return max(ratios)


def draw_heat_maps(rows: list[dict], plan, out: Path) -> list[Path]:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415
    from matplotlib.colors import LogNorm  # noqa: PLC0415

    from .stability import names_cause  # noqa: PLC0415
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
                grid[i][j] = worst_ratio(row)
                met, told = str(row["meets_targets"]) == "True", str(row["detected"]) == "True"
                mark = "met" if met else ("told" if told and names_cause(row) else "told, not why" if told else "SILENT")
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
