"""``renderer_retries``: 4 (the default before issue 58), 1 (the default since) and 0 (a rejected step after a
kept one ends a renderer pass), side by side in one run (on demand: ``pytest -m bench
tests/bench/test_bench_renderer_retries.py -s``; about twenty minutes on two cores, less where the sessions exist).

Sessions (``demo_sessions.py``): the demo's of seeds 0 and 1 (256², no hairs) and of seed 0 with the
scene's hairs (``configs/scene.yaml``, where 0 costs β_m its target). Per session and setting:
wall seconds of the fit (two threads; the two settings alternate, old first), renders, the finest
level's iterations, each map's median error against the truth over the scored pixels
(``skinlayers.demo.accuracy_against_truth``; relative, β_m absolute), the residual, and σ coverage (the
share of scored pixels whose truth lies within 2σ). Writes ``renderer_retries.csv``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from bench_io import write_csv
from demo_sessions import calibrated_session, refit

pytestmark = pytest.mark.bench

SESSIONS = {"seed 0": ("uncertainty_seed0", 0, None), "seed 1": ("uncertainty_seed1", 1, None),
            "seed 0, hairs": ("hairs_seed0", 0, str(Path(__file__).resolve().parents[2] / "configs" / "scene.yaml"))}
RETRIES = (4, 1, 0)
MAPS = ("C_m", "beta_m", "C_he", "C_hd")


def test_renderer_retries_one_and_none_against_four():
    from skinlayers.demo import scored_pixels, sigma_coverage
    from skinlayers.model.patch.maps_io import read_maps
    from skinlayers.reconstruct.settings import FitSettings

    rows = []
    for label, (name, seed, scene) in SESSIONS.items():
        folder = calibrated_session(name, seed, scene)
        truth = read_maps(folder / "session" / "truth" / "maps.exr")
        for retries in RETRIES:
            fit, accuracy = refit(folder, FitSettings(renderer_retries=retries), f"retries_{retries}")
            row = {"session": label, "renderer_retries": retries, "wall_s": round(fit.wall_s, 1),
                   "renders": sum(level["forward_renders"] for level in fit.levels),
                   "finest_iterations": fit.kept_levels[-1]["iterations_per_pass"]}
            row.update({f"err_{n}": round(v["median_error"], 4) for n, v in accuracy["parameters"].items()})
            row["residual_rms"] = round(accuracy["residual_rms"], 5)
            cover = sigma_coverage(truth, fit.maps, fit.sigma, scored_pixels(fit.flags), MAPS)
            row.update({f"cover_{m}": round(v, 3) for m, v in cover.items()})
            rows.append(row)
    write_csv("renderer_retries.csv", rows, "renderer passes: retries after progress 4, 1 and 0, side by side")
    for k in range(0, len(rows), len(RETRIES)):
        assert rows[k + 1]["renders"] < rows[k]["renders"], rows[k: k + len(RETRIES)]
