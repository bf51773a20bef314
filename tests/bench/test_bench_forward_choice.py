"""The forward model chosen per cube (``forward: auto``, ``reconstruct/choice/fidelity.py``) against the
renderer's fit, side by side in one run (on demand:
``pytest -m bench tests/bench/test_bench_forward_choice.py -s``).

Scenes (``tests/reconstruct/synthetic_cubes.py``: rendered at higher fidelity than the fit, real
occluded skin around the window, 5-point bands, camera noise at the rig's level): a flat patch (IV
exterior, no variation, no features) at 128² and at 256² (the 256² rendered at the cube's own grid,
``fine=1``, to keep its render under ten minutes here), smooth skin (the scene's variation, no
features) and the full small scene (variation, two freckles, a scar, a vein) at 128². Per scene and
forward setting: wall and process CPU seconds of ``fit_cube`` (two threads), each map's median error
against the truth (relative; β_m absolute), what ``auto`` chose and its checks. Writes
``forward_choice.csv``; ``-k uniform`` the flat patches alone, ``uniform_patch.csv``.
"""

from __future__ import annotations

import json
import time

import pytest
import torch

from bench_io import write_csv
from reconstruct_run import synthetic

pytestmark = pytest.mark.bench

#: name → make_cube keywords
SCENES = {
    "flat patch 128²": dict(size_px=128, features=False, variation=0.0),
    "flat patch 256² (fine=1)": dict(size_px=256, features=False, variation=0.0, fine=1),
    "smooth skin 128²": dict(size_px=128, features=False),
    "freckles, scar, vein 128²": dict(size_px=128),
}


def _errors(fit, syn) -> dict:
    from skinlayers.model import PARAMETER_NAMES

    mask = syn.cube.mask
    out = {}
    for name in PARAMETER_NAMES:
        got, want = getattr(fit.maps, name)[0][mask].double(), getattr(syn.truth, name)[0][mask].double()
        err = (got - want).abs() if name == "beta_m" else (got - want).abs() / want.abs().clamp_min(1e-9)
        out[f"err_{name}"] = round(float(err.median()), 4)
    return out


def _side_by_side(scenes: dict[str, dict]) -> list[dict]:
    """Every scene fitted by the renderer's fit and by ``auto``, one after the other in this process."""
    from skinlayers.reconstruct.mapfit.fit import fit_cube
    from skinlayers.reconstruct.settings import FitSettings

    torch.set_num_threads(2)
    sc = synthetic()
    rows = []
    for scene, kw in scenes.items():
        syn = sc.make_cube(seed=5, preset="IV exterior", noise=1.0, blur="pyramid", **kw)
        fit_cube(syn.cube, FitSettings(max_iterations=1, forward="heterogeneous"))  # tables built outside the timings
        for forward in ("heterogeneous", "auto"):
            start, cpu = time.perf_counter(), time.process_time()
            fit = fit_cube(syn.cube, FitSettings(forward=forward))
            wall, cpu = time.perf_counter() - start, time.process_time() - cpu
            choice = fit.forward_choice or {}
            chosen = choice.get("chosen", "heterogeneous")
            rows.append({"scene": scene, "forward": forward, "wall_s": round(wall, 2), "cpu_s": round(cpu, 2), **_errors(fit, syn),
                         "chosen": "uniform" if choice.get("uniform") else chosen,
                         "crosstalk_rms_noise": json.dumps([c["crosstalk_rms"] for c in choice.get("checks", [])]),
                         "homogeneous_wall_s": choice.get("homogeneous_wall_s", "")})
            print(rows[-1], flush=True)
    return rows


def test_forward_choice_against_the_renderer():
    rows = _side_by_side(SCENES)
    write_csv("forward_choice.csv", rows, "auto against the renderer, side by side")
    flat = [r for r in rows if r["scene"].startswith("flat") and r["forward"] == "auto"]
    assert all(r["chosen"] in ("homogeneous", "uniform") for r in flat)


def test_uniform_patch_against_the_renderer():
    """The two flat patches alone (``-k uniform``): uniform skin found, its speed-up and maps."""
    rows = _side_by_side({k: v for k, v in SCENES.items() if k.startswith("flat")})
    write_csv("uniform_patch.csv", rows, "uniform skin against the renderer, side by side")
    assert all(r["chosen"] == "uniform" for r in rows if r["forward"] == "auto")
