"""``report.png``: measured against fitted reflectance per band (DWRR08 Fig. 11) and the fitted maps
with residual and flags (Fig. 12), with matplotlib's non-interactive backend.

Rows: measured, fitted (same colour range per band), fitted − measured (symmetric range); then the
five parameter maps, the per-pixel residual RMS and the flags. Masked pixels are drawn grey. A map of one
value for the patch, or one the data leave undetermined, gets its value or the reason in its title and
no colour bar (a bar would claim a range); the flags panel draws each pixel's first flag in its own
colour, with a legend of the flags present and their shares. Colour bars carry plain tick labels (no
offset text above the bar to run into the title).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ...model import PARAMETER_NAMES
from ..diagnosis.checks import FLAG_BITS, first_flag
from ..mapfit.fit import MapFit

__all__ = ["draw_report", "plot_report"]

#: The flags panel's colours, one per flag bit (tab10), and the order a pixel's first flag is drawn in.
_FLAG_COLOURS = "tab10"
#: The most bands drawn: a hyperspectral cube (tens of bands, or hundreds) shows this many, spread over its
#: range with the band that fits worst among them (what drawing every band cost: docs/reconstruct.md,
#: "Figures from the code").
REPORT_BANDS = 9
#: The PNG's resolution (dots per inch).
REPORT_DPI = 110

_LABELS = {"C_m": "melanin C_m", "beta_m": "eumelanin share β_m", "C_he": "epidermal blood C_he",
           "C_bc": "carotene C_bc", "C_hd": "dermal blood C_hd"}


def plot_report(fit: MapFit, measured: torch.Tensor, path: str | Path, undetermined: dict[str, str] | None = None) -> Path:
    """Draw the report of ``fit`` against ``measured`` ``(L, H, W)`` into ``path``; ``undetermined``: the
    maps the data leave undetermined, each with the few words why (drawn without a colour bar)."""
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig = draw_report(fit, measured, undetermined)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fig.savefig(path, dpi=REPORT_DPI)
    finally:
        plt.close(fig)
    return path


def draw_report(fit: MapFit, measured: torch.Tensor, undetermined: dict[str, str] | None = None):
    """The report's figure (matplotlib, Agg); the caller closes it."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415
    from matplotlib.ticker import FuncFormatter  # noqa: PLC0415

    undetermined = undetermined or {}
    plain = FuncFormatter(lambda v, _: f"{v:.3g}")

    masked = ((fit.flags >> FLAG_BITS["masked"]) & 1).bool().cpu().numpy()
    res = fit.residual.detach().cpu().numpy()
    band_rms = np.sqrt(np.mean(res[:, ~masked] ** 2, axis=1)) if (~masked).any() else np.zeros(len(res))
    shown = report_bands(band_rms)
    wl = fit.wavelength_nm.tolist()
    cols = max(len(shown), 7)
    fig, axes = plt.subplots(4, cols, figsize=(1.9 * cols, 8.4), squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()

    def show(ax, img, title, cmap="viridis", vmin=None, vmax=None, bar=True):
        a = np.ma.masked_array(img, masked)
        cm = plt.get_cmap(cmap).with_extremes(bad="0.6")
        im = ax.imshow(a, cmap=cm, vmin=vmin, vmax=vmax, interpolation="nearest")
        ax.set_title(title, fontsize=7)
        if bar:
            cbar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02, format=plain)
            cbar.ax.tick_params(labelsize=5)

    meas = measured.detach().cpu().numpy()
    fitted = fit.image.detach().cpu().numpy()
    for col, j in enumerate(shown):
        w = wl[j]
        vis = meas[j][~masked]
        lo, hi = (float(np.percentile(vis, 1)), float(np.percentile(vis, 99))) if vis.size else (0.0, 1.0)
        used = bool(fit.checks.bands_used[j])
        show(axes[0, col], meas[j], f"measured {w:g} nm" + ("" if used else " (left out)"), "gray", lo, hi)
        show(axes[1, col], fitted[j], f"fitted {w:g} nm", "gray", lo, hi)
        lim = float(np.percentile(np.abs(res[j][~masked]), 99)) if vis.size else 1.0
        show(axes[2, col], res[j], f"fit − measured {w:g}", "RdBu_r", -lim, lim)
    _map_panels(axes[3], fit, masked, undetermined, show)
    show(axes[3, 5], fit.residual_rms.detach().cpu().numpy(), "residual RMS", "inferno")
    _flags_panel(axes[3, 6], fit.flags.cpu().numpy(), plt)
    title = (f"scale {fit.scale:.3f} · residual RMS {float(fit.residual_rms[~torch.from_numpy(masked)].pow(2).mean().sqrt()):.4f} · "
             f"{fit.cpu_s:.1f} s CPU")
    if len(shown) < len(wl):
        title += f" · {len(shown)} of {len(wl)} bands drawn (spread over the range, the worst fit {wl[int(np.argmax(band_rms))]:g} nm among them)"
    if fit.forward_choice:  # the forward model and why (reconstruct/choice/fidelity.py)
        title += f"\nforward model: {fit.forward_choice['chosen']} — {fit.forward_choice['reason']}"
    fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    return fig


def _map_panels(row, fit: MapFit, masked: np.ndarray, undetermined: dict[str, str], show) -> None:
    """The five parameter maps into the axes ``row``; ``show(ax, img, title, cmap, vmin, vmax, bar)`` draws one."""
    for i, n in enumerate(PARAMETER_NAMES):
        values = getattr(fit.maps, n)[0].detach().cpu().numpy()
        vis = values[~masked] if (~masked).any() else values.ravel()
        lo, hi = float(vis.min()), float(vis.max())
        if n in undetermined:
            show(row[i], values, f"{_LABELS[n]}\nundetermined: {undetermined[n]}", "magma", bar=False)
        elif hi - lo <= 1e-3 * max(abs(hi), 1e-12):  # one value for the patch (a map on one node): no round-off speckle
            lo, hi = lo * 0.9, hi * 1.1 + 1e-12
            show(row[i], values, f"{_LABELS[n]}\n= {np.median(vis):.3g} (patch)", "magma", lo, hi, bar=False)
        else:
            show(row[i], values, _LABELS[n], "magma")


def report_bands(band_rms: np.ndarray, most: int = REPORT_BANDS) -> list[int]:
    """The bands drawn, by index: all of them up to ``most``; beyond, ``most`` spread evenly from the first
    to the last, the inner one nearest the worst fit (largest ``band_rms`` ``(L,)``) replaced by it."""
    n = len(band_rms)
    if n <= most:
        return list(range(n))
    picks = [int(round(v)) for v in np.linspace(0, n - 1, most)]
    worst = int(np.argmax(band_rms))
    if worst not in picks:
        inner = range(1, most - 1)  # the ends stay: the drawn bands span the range
        picks[min(inner, key=lambda k: abs(picks[k] - worst))] = worst
    return sorted(picks)


def _flags_panel(ax, flags: np.ndarray, plt) -> None:
    """Each pixel in the colour of its first flag (white: none), a legend of the flags present below."""
    from matplotlib.colors import ListedColormap  # noqa: PLC0415
    from matplotlib.patches import Patch  # noqa: PLC0415

    colours = plt.get_cmap(_FLAG_COLOURS).colors
    cmap = ListedColormap(["white", *colours[: len(FLAG_BITS)]])
    ax.set_axis_on()
    ax.imshow(first_flag(flags), cmap=cmap, vmin=0, vmax=len(FLAG_BITS), interpolation="nearest")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title("flags (first set)", fontsize=7)
    present = [(name, bit, float(((flags >> bit) & 1).mean())) for name, bit in FLAG_BITS.items() if ((flags >> bit) & 1).any()]
    handles = [Patch(color=colours[bit], label=f"{name} {share:.1%}") for name, bit, share in present]
    if not handles:
        handles = [Patch(facecolor="white", edgecolor="0.5", label="no flag")]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.04), fontsize=5, frameon=False, ncol=1,
              handlelength=1.0, borderaxespad=0.0)
