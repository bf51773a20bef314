"""The finest level's robust weighting, ``robust_finest: carry`` (the default) against ``refit``, side
by side in one run (on demand: ``pytest -m bench tests/bench/test_bench_robust_finest.py -s``; about
fifteen minutes on two cores, less where the sessions exist).

Sessions (``demo_sessions.py``): the demo's of seeds 0 and 1 (no hairs) and the demo's scene with its
five hairs (``configs/scene.yaml``, seed 0). Per session and setting: wall seconds of the fit (two
threads), the iterations of the finest level, and each map's median error against the truth over the
pixels not flagged for a high residual (``skinlayers.demo.accuracy_against_truth``; relative, β_m
absolute). Writes ``robust_finest.csv``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from bench_io import write_csv
from demo_sessions import calibrated_session, refit

pytestmark = pytest.mark.bench

SCENE_WITH_HAIRS = str(Path(__file__).resolve().parents[2] / "configs" / "scene.yaml")
SESSIONS = {"seed 0": ("uncertainty_seed0", 0, None), "seed 1": ("uncertainty_seed1", 1, None),
            "seed 0, five hairs": ("robust_hairs_seed0", 0, SCENE_WITH_HAIRS)}


def test_robust_finest_carry_against_refit():
    from skinlayers.reconstruct.settings import FitSettings

    rows = []
    for label, (name, seed, scene) in SESSIONS.items():
        folder = calibrated_session(name, seed, scene)
        for setting in ("refit", "carry"):
            fit, accuracy = refit(folder, FitSettings(robust_finest=setting), f"robust_{setting}")
            row = {"session": label, "robust_finest": setting, "wall_s": round(fit.wall_s, 1),
                   "finest_iterations": fit.kept_levels[-1]["iterations_per_pass"]}
            row.update({f"err_{n}": round(v["median_error"], 4) for n, v in accuracy["parameters"].items()})
            row["residual_rms"] = round(accuracy["residual_rms"], 5)
            rows.append(row)
    write_csv("robust_finest.csv", rows, "finest level: carried weights against a refit, side by side")
    for a, b in zip(rows[::2], rows[1::2]):
        assert b["finest_iterations"] and len(b["finest_iterations"]) == 1 and len(a["finest_iterations"]) == 2
