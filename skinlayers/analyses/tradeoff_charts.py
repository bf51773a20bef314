"""The tradeoff's charts: time (log) against error, the Pareto front drawn, the default, the ``auto``
choice and the paper's configuration marked and labelled; cost against the cube's size."""

from __future__ import annotations

from pathlib import Path

__all__ = ["draw_charts"]

#: How the marked configurations are drawn: colour and label.
MARKS = {"default": ("tab:red", "default (--model auto)"), "fixed": ("tab:orange", "--model fixed"),
         "paper": ("tab:blue", "DWRR08's scheme"), "paper, 10 steps": ("tab:blue", "DWRR08's scheme, 10 steps")}
FORWARD_MARKS = {"default": ("tab:red", "default"), "paper": ("tab:blue", "DWRR08's renderer")}


def draw_charts(rows: list[dict], summary: dict, out: Path) -> list[Path]:
    """``tradeoff_forward.png``, ``tradeoff_inverse.png`` and ``tradeoff_scale.png`` (those with data)."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    paths = []
    groups = summary["groups"]
    forward = [g for g in ("forward vs Monte Carlo", "forward vs own") if g in groups]
    if forward:
        fig, axes = plt.subplots(1, len(forward), figsize=(6.2 * len(forward), 4.8), squeeze=False)
        titles = {"forward vs Monte Carlo": "the renderer against the Monte Carlo\n(RMS relative error, its noise taken out)",
                  "forward vs own": "against its own physics at full fidelity\n(the numerical error alone)"}
        for ax, name in zip(axes[0], forward):
            _panel(ax, groups[name], titles[name], "render time (s, five scenes' mean)", "RMS relative error", FORWARD_MARKS)
        fig.tight_layout()
        paths.append(_save(fig, out / "tradeoff_forward.png", plt))
    inverse = [g for g in ("inverse vs diffusion", "inverse vs transport", "inverse vs none") if g in groups]
    if inverse:
        fig, axes = plt.subplots(1, len(inverse), figsize=(6.2 * len(inverse), 4.8), squeeze=False)
        titles = {"inverse vs diffusion": "sessions rendered by the model (higher fidelity)",
                  "inverse vs transport": "sessions rendered by the Monte Carlo",
                  "inverse vs none": "your cube: distance from the most faithful fit"}
        for ax, name in zip(axes[0], inverse):
            _panel(ax, groups[name], titles[name], "fit time (s, wall)", "score: mean of map error / target", MARKS)
            if name != "inverse vs none":
                ax.axhline(1.0, color="0.6", lw=0.8, ls=":")
        fig.tight_layout()
        paths.append(_save(fig, out / "tradeoff_inverse.png", plt))
    if summary.get("scale"):
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
        for config, entry in summary["scale"].items():
            colour = MARKS.get(config, ("k", config))[0]
            label = MARKS.get(config, (None, config))[1] + (f", k = {entry['exponent']:.2f}" if "exponent" in entry else "")
            axes[0].loglog(entry["pixels"], entry["wall_s"], "o-", color=colour, label=label)
            axes[1].loglog(entry["pixels"], [max(v, 1e-1) for v in entry["peak_mb"]], "o-", color=colour, label=config)
        axes[0].set(xlabel="cube pixels", ylabel="fit time (s, wall)", title="time ∝ pixels^k")
        axes[1].set(xlabel="cube pixels", ylabel="peak memory added (MB)", title="peak memory")
        for ax in axes:
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=8)
        fig.tight_layout()
        paths.append(_save(fig, out / "tradeoff_scale.png", plt))
    return paths


def _panel(ax, group: dict, title: str, xlabel: str, ylabel: str, marks: dict) -> None:
    from matplotlib.ticker import FormatStrFormatter, NullFormatter  # noqa: PLC0415

    configs = group["configs"]
    pts = [(name, e["wall_s"], e["error"], e["pareto"]) for name, e in configs.items() if e["error"] is not None]
    for name, t, err, on_front in pts:
        if name in marks:  # the marked ones in the legend, drawn large
            colour, label = marks[name]
            ax.scatter([t], [err], s=90, color=colour, zorder=4, edgecolor="k" if on_front else "none", label=label)
        else:
            ax.scatter([t], [err], s=22, color="0.35", zorder=3, edgecolor="tab:green" if on_front else "none", linewidth=1.5)
            ax.annotate(name, (t, err), fontsize=7, xytext=(4, -9), textcoords="offset points", color="0.25")
    front = sorted((t, err) for _, t, err, f in pts if f)
    if front:
        xs, ys = [], []
        for t, err in front:  # a staircase: nothing below it at less time
            if xs:
                xs.append(t)
                ys.append(ys[-1])
            xs.append(t)
            ys.append(err)
        ax.plot(xs, ys, "-", color="tab:green", lw=1.2, label="Pareto front", zorder=2)
    ax.set_xscale("log")
    errors = [err for _, _, err, _ in pts]
    if errors and min(errors) > 0 and max(errors) / min(errors) > 30:  # a wide spread of errors reads better in log
        ax.set_yscale("log")
    ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.margins(x=0.12, y=0.08)
    ax.legend(fontsize=8, loc="best")
    ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
    ax.title.set_fontsize(10)
    ax.grid(alpha=0.3, which="both")


def _save(fig, path: Path, plt) -> Path:
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
