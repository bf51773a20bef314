"""``renderer_retries: 0`` (the default: a rejected step after a kept one ends a renderer pass) against
the previous 4, side by side in one run (on demand: ``pytest -m bench tests/bench/test_bench_renderer_retries.py -s``;
about ten minutes on two cores, less where the sessions exist).

Sessions (``demo_sessions.py``): the demo's of seeds 0 and 1 (256², no hairs). Per session and setting:
wall seconds of the fit (two threads; the two settings alternate, old first), renders, the finest
level's iterations, each map's median error against the truth over the scored pixels
(``skinlayers.demo.accuracy_against_truth``; relative, β_m absolute), the residual, and σ coverage (the
share of scored pixels whose truth lies within 2σ). Writes ``renderer_retries.csv``.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from bench_io import write_csv  # noqa: E402
from demo_sessions import calibrated_session, refit  # noqa: E402

pytestmark = pytest.mark.bench

SESSIONS = {"seed 0": ("uncertainty_seed0", 0), "seed 1": ("uncertainty_seed1", 1)}
MAPS = ("C_m", "beta_m", "C_he", "C_hd")


def sigma_cover(folder, name: str) -> dict[str, float]:
    """Per map, the share of the fit's scored pixels whose truth (box-averaged to the fit's grid) lies within 2σ."""
    from skinlayers.demo import scored_pixels
    from skinlayers.formats.exr import read_exr
    from skinlayers.model.maps_io import read_maps

    truth = read_maps(folder / "session" / "truth" / "maps.exr")
    channels, _ = read_exr(folder / name / "maps.exr")
    keep = scored_pixels(torch.as_tensor(np.asarray(channels["flags"])).long()).numpy()
    out = {}
    for m in MAPS:
        fit, sigma = np.asarray(channels[m]), np.asarray(channels[f"sigma_{m}"])
        t = getattr(truth, m)[None].double()
        k = t.shape[-1] // fit.shape[-1]
        t = (F.avg_pool2d(t, k) if k > 1 else t)[0, 0].numpy()
        out[m] = round(float((np.abs(fit - t) <= 2 * sigma)[keep].mean()), 3)
    return out


def test_renderer_retries_none_against_four():
    from skinlayers.reconstruct.settings import FitSettings

    rows = []
    for label, (name, seed) in SESSIONS.items():
        folder = calibrated_session(name, seed)
        for retries in (4, 0):
            fit, accuracy = refit(folder, FitSettings(renderer_retries=retries), f"retries_{retries}")
            row = {"session": label, "renderer_retries": retries, "wall_s": round(fit.wall_s, 1),
                   "renders": sum(level["forward_renders"] for level in fit.levels),
                   "finest_iterations": fit.kept_levels[-1]["iterations_per_pass"]}
            row.update({f"err_{n}": round(v["median_error"], 4) for n, v in accuracy["parameters"].items()})
            row["residual_rms"] = round(accuracy["residual_rms"], 5)
            row.update({f"cover_{m}": v for m, v in sigma_cover(folder, f"retries_{retries}").items()})
            rows.append(row)
    write_csv("renderer_retries.csv", rows, "renderer passes: no retry after progress against four, side by side")
    for old, new in zip(rows[::2], rows[1::2]):
        assert new["renders"] < old["renders"]
