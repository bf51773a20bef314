"""``report.png``: measured against fitted reflectance per band (DWRR08 Fig. 11) and the fitted maps
with residual and flags (Fig. 12), with matplotlib's non-interactive backend.

Rows: measured, fitted (same colour range per band), fitted − measured (symmetric range); then the
five parameter maps, the per-pixel residual RMS and the flags. Masked pixels are drawn grey.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ...model import PARAMETER_NAMES
from ..diagnosis.checks import FLAG_BITS
from ..mapfit.fit import MapFit

__all__ = ["plot_report"]

_LABELS = {"C_m": "melanin C_m", "beta_m": "eumelanin share β_m", "C_he": "epidermal blood C_he",
           "C_bc": "carotene C_bc", "C_hd": "dermal blood C_hd"}


def plot_report(fit: MapFit, measured: torch.Tensor, path: str | Path) -> Path:
    """Draw the report of ``fit`` against ``measured`` ``(L, H, W)`` into ``path``."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    masked = ((fit.flags >> FLAG_BITS["masked"]) & 1).bool().cpu().numpy()
    wl = fit.wavelength_nm.tolist()
    n_bands = len(wl)
    cols = max(n_bands, 7)
    fig, axes = plt.subplots(4, cols, figsize=(1.9 * cols, 8.4), squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()

    def show(ax, img, title, cmap="viridis", vmin=None, vmax=None):
        a = np.ma.masked_array(img, masked)
        cm = plt.get_cmap(cmap).with_extremes(bad="0.6")
        im = ax.imshow(a, cmap=cm, vmin=vmin, vmax=vmax, interpolation="nearest")
        ax.set_title(title, fontsize=7)
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02).ax.tick_params(labelsize=5)

    meas = measured.detach().cpu().numpy()
    fitted = fit.image.detach().cpu().numpy()
    res = fit.residual.detach().cpu().numpy()
    for j, w in enumerate(wl):
        vis = meas[j][~masked]
        lo, hi = (float(np.percentile(vis, 1)), float(np.percentile(vis, 99))) if vis.size else (0.0, 1.0)
        used = bool(fit.checks.bands_used[j])
        show(axes[0, j], meas[j], f"measured {w:g} nm" + ("" if used else " (left out)"), "gray", lo, hi)
        show(axes[1, j], fitted[j], f"fitted {w:g} nm", "gray", lo, hi)
        lim = float(np.percentile(np.abs(res[j][~masked]), 99)) if vis.size else 1.0
        show(axes[2, j], res[j], f"fit − measured {w:g}", "RdBu_r", -lim, lim)
    for i, n in enumerate(PARAMETER_NAMES):
        values = getattr(fit.maps, n)[0].detach().cpu().numpy()
        vis = values[~masked] if (~masked).any() else values.ravel()
        lo, hi = float(vis.min()), float(vis.max())
        if hi - lo <= 1e-3 * max(abs(hi), 1e-12):  # one value for the patch (a map on one node): no round-off speckle
            lo, hi = lo * 0.9, hi * 1.1 + 1e-12
            show(axes[3, i], values, f"{_LABELS[n]} = {np.median(vis):.3g} (patch)", "magma", lo, hi)
        else:
            show(axes[3, i], values, _LABELS[n], "magma")
    show(axes[3, 5], fit.residual_rms.detach().cpu().numpy(), "residual RMS", "inferno")
    axes[3, 6].set_axis_on()
    axes[3, 6].imshow(fit.flags.cpu().numpy(), cmap="tab10", interpolation="nearest", vmin=0, vmax=2 ** len(FLAG_BITS))
    axes[3, 6].set_title("flags (bit field)", fontsize=7)
    axes[3, 6].set_xticks([])
    axes[3, 6].set_yticks([])
    title = (f"scale {fit.scale:.3f} · residual RMS {float(fit.residual_rms[~torch.from_numpy(masked)].pow(2).mean().sqrt()):.4f} · "
             f"{fit.cpu_s:.1f} s CPU")
    if fit.forward_choice:  # the forward model and why (reconstruct/choice/fidelity.py)
        title += f"\nforward model: {fit.forward_choice['chosen']} — {fit.forward_choice['reason']}"
    fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
