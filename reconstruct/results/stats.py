"""Statistics of fitted maps as DWRR08 §7 reports them: trimmed per-parameter statistics, correlations,
principal components; and the residual's statistics.

Trimming: DWRR08 computes its Table 2 means after discarding the outer 5% on each side (the 5–95
percentile range); ``trimmed_stats`` does the same per parameter over the visible pixels.
Correlations are Pearson's over the visible pixels, among the five maps and for the pairs the paper
quotes: dermal–epidermal blood (0.87 in the paper) and eumelanin C_m·β_m – pheomelanin C_m·(1−β_m)
(0.034). PCA is over the five maps standardised to unit variance (the paper: four components explain
98.7%).

Shapes: maps ``(5, N)`` over the N pixels used.
"""

from __future__ import annotations

import math

import torch

from ...model import PARAMETER_NAMES

__all__ = ["correlations", "pca_explained", "residual_stats", "trimmed_stats"]


def trimmed_stats(values: torch.Tensor, lo_q: float = 0.05, hi_q: float = 0.95) -> dict[str, float]:
    """Mean, std and median of ``values`` ``(N,)`` within its [lo_q, hi_q] quantiles, plus the quantiles,
    min and max of all values."""
    v = values.double().reshape(-1)
    lo, hi = torch.quantile(v, lo_q), torch.quantile(v, hi_q)
    kept = v[(v >= lo) & (v <= hi)]
    return {
        "mean": float(kept.mean()),
        "std": float(kept.std(unbiased=True)) if kept.numel() > 1 else 0.0,
        "median": float(kept.median()),
        f"p{round(lo_q * 100)}": float(lo),
        f"p{round(hi_q * 100)}": float(hi),
        "min": float(v.min()),
        "max": float(v.max()),
        "pixels": int(v.numel()),
    }


def _pearson(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.double() - a.double().mean(), b.double() - b.double().mean()
    den = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
    return float((a * b).sum()) / den if den > 0 else float("nan")


def correlations(params: torch.Tensor) -> dict:
    """Pearson correlations: the 5×5 matrix and the paper's two pairs, ``params`` ``(5, N)``."""
    c = {n: params[i] for i, n in enumerate(PARAMETER_NAMES)}
    matrix = [[_pearson(params[i], params[j]) for j in range(5)] for i in range(5)]
    return {
        "names": list(PARAMETER_NAMES),
        "matrix": matrix,
        "dermal_epidermal_blood": _pearson(c["C_hd"], c["C_he"]),
        "eumelanin_pheomelanin": _pearson(c["C_m"] * c["beta_m"], c["C_m"] * (1.0 - c["beta_m"])),
        "paper": {"dermal_epidermal_blood": 0.87, "eumelanin_pheomelanin": 0.034},
    }


def pca_explained(params: torch.Tensor, target: float = 0.987) -> dict:
    """Explained variance ratios of the standardised maps ``(5, N)`` and the components needed for
    ``target`` of the variance (the paper: 4 for 98.7%). Constant maps are left out."""
    x = params.double()
    std = x.std(dim=1, keepdim=True)
    keep = (std[:, 0] > 0) & torch.isfinite(std[:, 0])
    if int(keep.sum()) == 0 or x.shape[1] < 2:
        return {"explained_ratio": [], "cumulative": [], "components_for_target": 0, "target": target, "paper_components": 4}
    z = (x[keep] - x[keep].mean(dim=1, keepdim=True)) / std[keep]
    eig = torch.linalg.eigvalsh(z @ z.T / (z.shape[1] - 1)).flip(0).clamp_min(0.0)
    ratio = eig / eig.sum()
    cum = torch.cumsum(ratio, 0)
    need = int((cum < target - 1e-12).sum()) + 1
    return {
        "explained_ratio": [float(v) for v in ratio],
        "cumulative": [float(v) for v in cum],
        "components_for_target": min(need, int(ratio.numel())),
        "target": target,
        "standardised_maps": [n for n, k in zip(PARAMETER_NAMES, keep.tolist()) if k],
        "paper_components": 4,
    }


def residual_stats(residual: torch.Tensor, residual_rms: torch.Tensor, wavelength_nm: list[float], used: list[bool]) -> dict:
    """Residuals over the pixels in the loss: ``residual`` ``(L, N)``, ``residual_rms`` ``(N,)``."""
    bands = {}
    for j, w in enumerate(wavelength_nm):
        r = residual[j].double()
        bands[f"{w:g}"] = {"rms": float(torch.sqrt((r * r).mean())), "mean": float(r.mean()), "used": bool(used[j])}
    rr = residual_rms.double()
    sel = residual[torch.tensor(used)].double()
    return {
        "rms": float(torch.sqrt((sel * sel).mean())),
        "pixel_rms_median": float(rr.median()),
        "pixel_rms_p95": float(torch.quantile(rr, 0.95)),
        "pixel_rms_max": float(rr.max()),
        "fraction_below_3_percent": float((rr < 0.03).double().mean()),
        "per_band": bands,
    }
