"""The napari dock widget: at the pixel under the cursor, the cube's spectrum with its noise (two σ either
side), the fitted one, the maps with their σ and the flags set there (``FitAtPixels`` reads them; this draws them, in Qt)."""

from __future__ import annotations

from qtpy.QtWidgets import QLabel, QVBoxLayout, QWidget

from .inspector import FitAtPixels, PixelReport

__all__ = ["PixelInspector"]

#: The spectrum panel's size (inches at matplotlib's 100 dpi).
FIGURE_IN = (4.0, 2.6)


class PixelInspector(QWidget):
    """Follows ``viewer``'s cursor over the first layer a skinlayers maps file opened; ``report`` holds
    what it shows now (None away from the maps)."""

    def __init__(self, napari_viewer) -> None:
        from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg  # noqa: PLC0415
        from matplotlib.figure import Figure  # noqa: PLC0415

        super().__init__()
        self.viewer = napari_viewer
        self.report: PixelReport | None = None
        self._fits: dict[str, FitAtPixels] = {}
        self.figure = Figure(figsize=FIGURE_IN, layout="constrained")
        self.canvas = FigureCanvasQTAgg(self.figure)
        self.text = QLabel("move the cursor over a fit's maps")
        self.text.setWordWrap(True)
        layout = QVBoxLayout(self)
        layout.addWidget(self.canvas)
        layout.addWidget(self.text)
        napari_viewer.cursor.events.position.connect(self._moved)

    def fit(self) -> FitAtPixels | None:
        """The fit of the first maps layer in the viewer (read once), None where none is open."""
        for layer in self.viewer.layers:
            meta = layer.metadata.get("skinlayers", {})
            if meta.get("kind") == "map":
                path = meta["path"]
                if path not in self._fits:
                    self._fits[path] = FitAtPixels(path)
                return self._fits[path]
        return None

    def _moved(self, event=None) -> None:
        fit = self.fit()
        position = self.viewer.cursor.position
        pixel = fit.pixel_of(*position[-2:]) if fit is not None and len(position) >= 2 else None
        if pixel is None:
            return
        self.show_report(fit.at(*pixel), fit.cube_problem)

    def show_report(self, report: PixelReport, note: str = "") -> None:
        """Draw ``report``: the spectra above, the parameters and flags below (and ``note``: why no cube)."""
        self.report = report
        self.figure.clear()
        ax = self.figure.add_subplot()
        wl = report.wavelength_nm
        if report.measured is not None:
            ax.errorbar(wl, report.measured, yerr=2.0 * report.noise_sigma, fmt="o", ms=3, color="k", label="measured ±2σ")
        if report.fitted is not None:
            ax.plot(wl, report.fitted, "-", color="tab:red", label="fitted")
        ax.set_xlabel("wavelength (nm)", fontsize=8)
        ax.set_ylabel("reflectance", fontsize=8)
        ax.tick_params(labelsize=7)
        if report.measured is not None:
            ax.legend(fontsize=7, frameon=False)
        self.canvas.draw_idle()
        self.text.setText("\n".join(report.lines() + ([f"no spectra: {note}"] if note else [])))
