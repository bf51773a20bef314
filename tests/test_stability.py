"""``skinlayers stability``: the conditions do what they say to a cube, a cell's verdict and the summary
on constructed rows, and a small matrix on a simulated 16² session where every failing cell is told, and
one goes silent when the fit's checks are switched off."""

from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import pytest
import torch

from skinlayers.formats.cube import Cube, CubeHeader
from skinlayers.analyses.stability import (COLUMNS, CONDITIONS, METHODS, RESIDUAL_AT_NOISE, SIGMA_COVER, StabilityPlan, _perturb_cube,
                                  cell_verdict, make_plan, run_stability, summarise)
from skinlayers.reconstruct.diagnosis.checks import (MAP_TARGETS, RESIDUAL_NOISE_LIMIT, SMOOTH_BAND_RATIO, precision_notes, residual_notes,
                                          smooth_band_notes)

WAVELENGTHS_NM = (430.0, 460.0, 490.0, 520.0, 550.0, 580.0, 610.0, 640.0, 670.0)


def _cube(reflectance: torch.Tensor) -> Cube:
    header = CubeHeader(wavelengths_nm=list(WAVELENGTHS_NM), mm_per_pixel=0.1)
    return Cube(reflectance, torch.ones(reflectance.shape[1:], dtype=torch.bool), header)


def test_cube_conditions_change_what_they_name_and_nothing_else():
    gen = torch.Generator().manual_seed(0)
    truth = 0.2 + 0.1 * torch.rand(9, 12, 12, generator=gen)
    noisy = truth + 0.01 * torch.randn(9, 12, 12, generator=gen)
    cube = _cube(noisy)
    scaled = _perturb_cube(cube, truth, "noise", 4.0).reflectance
    torch.testing.assert_close(scaled - truth, 4.0 * (noisy - truth))
    dead = _perturb_cube(cube, truth, "dead band", 550).reflectance
    assert float(dead[4].max()) < 1e-3 and torch.equal(dead[5:], noisy[5:])
    step = torch.zeros(9, 12, 12)
    step[:, :, 6:] = 1.0
    moved = _perturb_cube(_cube(step), step, "misregistration", 2.0).reflectance
    # neighbouring bands one pixel each way: the step's position differs by 2 px between them
    assert float(moved[0, 0, 4]) == pytest.approx(0.0, abs=1e-6) and float(moved[0, 0, 5]) == pytest.approx(1.0, abs=1e-6)
    assert float(moved[1, 0, 6]) == pytest.approx(0.0, abs=1e-6) and float(moved[1, 0, 7]) == pytest.approx(1.0, abs=1e-6)
    blurred = _perturb_cube(_cube(step), step, "motion blur", 5).reflectance
    assert 0.0 < float(blurred[4, 0, 5]) < 1.0 and torch.equal(blurred[3], step[3])
    with pytest.raises(ValueError, match="not a cube condition"):
        _perturb_cube(cube, truth, "hairs", 5)


def _row(**over) -> dict:
    row = {f"error_{m}": 0.5 * t for m, t in MAP_TARGETS.items()}
    row.update(residual_over_noise=1.0, sigma_cover=0.9)
    row.update(over)
    return row


def test_a_cells_verdict_names_each_missed_target():
    assert cell_verdict(_row()) == []
    assert cell_verdict(_row(error_C_hd=0.11)) == ["C_hd"]
    assert cell_verdict(_row(error_beta_m=0.2, residual_over_noise=RESIDUAL_AT_NOISE * 1.01)) == ["beta_m", "residual"]
    assert cell_verdict(_row(sigma_cover=SIGMA_COVER - 0.01)) == ["sigma"]
    assert cell_verdict(_row(error_C_m=math.nan)) == ["C_m"]  # a NaN error is no success
    assert cell_verdict(_row(sigma_cover_flagged=0.7)) == ["sigma_flagged"]  # σ on a hair's pixels too
    assert cell_verdict(_row(sigma_cover_flagged=math.nan)) == [] and cell_verdict(_row(sigma_cover_flagged="")) == []


def test_the_summary_finds_breaking_points_silent_cells_and_false_alarms():
    plan = StabilityPlan({"noise": (0.25, 2.0, 4.0, 8.0), "certificate 430 nm": (-0.10, -0.05, 0.01)}, ["auto"])
    at = {"seed": str(plan.seed), "size_px": str(plan.size_px)}
    rows = [{"condition": "clean", "strength": "", "method": "auto", **at, "meets_targets": "True", "detected": "False", "missed": "", "message": ""}]
    cells = {("noise", "0.25"): (True, False), ("noise", "2"): (True, True), ("noise", "4"): (False, True), ("noise", "8"): (False, False),
             ("certificate 430 nm", "-0.1"): (False, False), ("certificate 430 nm", "-0.05"): (False, True), ("certificate 430 nm", "0.01"): (True, False)}
    for (c, s), (met, told) in cells.items():
        rows.append({"condition": c, "strength": s, "method": "auto", **at, "meets_targets": str(met), "detected": str(told),
                     "missed": "" if met else "C_m", "message": ("noise-limited maps" if c == "noise" else "a warning") if told else ""})
    summary = summarise(rows, plan)["methods"]["auto"]
    assert summary["breaking_points"]["noise"]["first_miss"] == 4.0
    assert summary["breaking_points"]["certificate 430 nm"]["first_miss"] == -0.05  # nearest the clean data
    assert [(s["condition"], s["strength"]) for s in summary["silent"]] == [("noise", "8"), ("certificate 430 nm", "-0.1")]
    assert [(s["condition"], s["strength"]) for s in summary["false_alarms"]] == [("noise", "2")]
    # told, but in words that do not name the condition
    assert [(s["condition"], s["strength"]) for s in summary["told_not_named"]] == [("certificate 430 nm", "-0.05")]
    assert summary["meeting_targets"] == 4 and summary["cells"] == 8
    # a method that misses a target on the clean session breaks where it misses another one
    plan.methods = ["auto", "gn-hom"]
    others = [{**r, "method": "gn-hom"} for r in rows]
    for r in others:
        r["missed"] = {"clean": "C_hd", "2": "C_hd", "4": "C_hd", "8": "C_hd C_m"}.get(r["strength"], r["missed"]) if r["condition"] in ("clean", "noise") else r["missed"]
        r["meets_targets"] = str(not r["missed"])
    others[0]["missed"] = "C_hd"
    other = summarise(rows + others, plan)["methods"]["gn-hom"]
    assert other["missed_clean"] == ["C_hd"]
    assert other["breaking_points"]["noise"]["first_miss"] == 8.0  # 2 and 4 miss only what clean misses
    assert other["breaking_points"]["certificate 430 nm"]["first_miss"] == -0.05
    # told in other words, missing only what the clean session misses: the method's own failure, not unnamed
    assert ("noise", "4") not in [(s["condition"], s["strength"]) for s in other["told_not_named"]]
    others[3]["message"] = "a warning"  # noise 4: told, not in the condition's words, C_hd only
    unnamed = [(s["condition"], s["strength"]) for s in summarise(rows + others, plan)["methods"]["gn-hom"]["told_not_named"]]
    assert ("noise", "4") not in unnamed and ("certificate 430 nm", "-0.05") in unnamed  # C_m beyond the clean miss


def test_the_fits_residual_and_precision_warnings_fire_beyond_their_limits_only():
    assert residual_notes(RESIDUAL_NOISE_LIMIT * 0.99) == [] and residual_notes(math.nan) == []
    assert "2.0× the cube's noise" in residual_notes(2.0)[0]
    # the expected median error of a normal error is 0.6745 σ
    assert precision_notes({n: 1.4 * t for n, t in MAP_TARGETS.items()} | {"C_bc": 5.0}) == []  # C_bc has no target
    line = precision_notes({"C_m": 0.3, "beta_m": 0.14, "C_hd": 0.2, "C_he": 0.3})[0]
    assert "C_m 20%" in line and "C_hd 13%" in line and "beta_m" not in line and "C_he" not in line
    assert "beta_m 0.11" in precision_notes({"beta_m": 0.16})[0]


def test_a_band_smoother_than_its_neighbours_is_named_and_only_it():
    wl = list(WAVELENGTHS_NM)
    clean = [8.6, 6.1, 5.1, 4.5, 5.2, 5.3, 5.7, 7.7, 16.6]  # a clean simulated cube's σ/reflectance (×1e-3)
    assert smooth_band_notes(clean, wl, [True] * 9) == []
    blurred = [*clean[:4], 1.0, *clean[5:]]
    line = smooth_band_notes(blurred, wl, [True] * 9)[0]
    assert "550 nm 0.20×" in line and "motion" in line and "520 nm" not in line
    # an end band has one neighbour; a band left out is no neighbour
    end = smooth_band_notes([*clean[:8], SMOOTH_BAND_RATIO * 0.9 * clean[7]], wl, [True] * 9)[0]
    assert "670 nm 0.45×" in end
    assert smooth_band_notes(blurred, wl, [True] * 4 + [False] + [True] * 4) == []
    assert "580 nm" in smooth_band_notes([*clean[:4], 1e-4, 1.0, *clean[6:]], wl, [True] * 4 + [False] + [True] * 4)[0]


def test_the_plans_name_known_conditions_and_methods():
    for quick in (True, False):
        plan = make_plan(quick)
        assert set(plan.conditions) == set(CONDITIONS) and set(plan.methods) <= set(METHODS)
        for name, strengths in plan.conditions.items():
            assert set(strengths) <= set(CONDITIONS[name].strengths), name


SMALL = {"noise": (8.0,), "misregistration": (2.0,), "dead band": (550,), "certificate 430 nm": (-0.08,)}


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    out = tmp_path_factory.mktemp("stability")
    said: list[str] = []
    result = run_stability(out, plan=StabilityPlan(dict(SMALL), ["gn-hom"], 16, seed=5), say=said.append)
    return out, result, said


def test_every_failing_cell_of_a_small_matrix_is_told(small):
    out, result, said = small
    with result.table.open() as f:
        reader = csv.DictReader(f)
        rows = list(reader)
    assert reader.fieldnames == list(COLUMNS)
    faults = [r for r in rows if r["condition"] != "clean"]
    assert [(r["condition"], r["method"]) for r in faults] == [(c, "gn-hom") for c in SMALL]
    for r in faults:
        assert r["meets_targets"] == "False", r  # each fault is strong enough to break the fit
        assert r["detected"] == "True" and r["message"], r
    assert "residual" in next(r for r in faults if r["condition"] == "misregistration")["message"]
    assert "550 nm left out" in next(r for r in faults if r["condition"] == "dead band")["message"]
    certificate = next(r for r in faults if r["condition"] == "certificate 430 nm")
    assert "card_spectrum 430 nm" in certificate["message"]
    # the noise is the right record's cube against the truth, not the wrong record's (that would hold the 8% too)
    clean = next(r for r in rows if r["condition"] == "clean")
    assert float(certificate["residual_over_noise"]) > 0.8 * float(clean["residual_over_noise"])
    summary = json.loads(result.summary_path.read_text())
    assert [s for s in summary["methods"]["gn-hom"]["silent"] if s["condition"] != "clean"] == []
    assert [p.name for p in result.charts] == ["stability_gn-hom.png"] and result.charts[0].stat().st_size > 0
    assert any("about" in line for line in said)  # progress with the time left


def _clean_row_only(out: Path, to: Path) -> None:
    """The small matrix's table with its clean cell alone, in ``to``: a run there resumes with the clean
    cell measured (the same session, the same fit) and measures only its faults."""
    with (out / "stability.csv").open() as f:
        reader = csv.DictReader(f)
        rows = [r for r in reader if r["condition"] == "clean"]
    with (to / "stability.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=reader.fieldnames)
        writer.writeheader()
        writer.writerows(rows)


def test_with_the_fits_checks_switched_off_a_failure_goes_silent(small, tmp_path, monkeypatch):
    out, _, _ = small
    shutil.copytree(out / "sessions", tmp_path / "sessions")  # the same session, not simulated again
    _clean_row_only(out, tmp_path)
    from skinlayers.reconstruct.diagnosis import checks

    monkeypatch.setattr(checks.DataChecks, "warn", lambda self, lines: None)
    result = run_stability(tmp_path, plan=StabilityPlan({"misregistration": (2.0,)}, ["gn-hom"], 16, seed=5), say=lambda s: None)
    silent = result.summary["methods"]["gn-hom"]["silent"]
    assert ("misregistration", "2") in [(s["condition"], s["strength"]) for s in silent]


def test_with_the_calibrations_card_check_switched_off_a_wrong_certificate_goes_silent(small, tmp_path, monkeypatch):
    out, _, _ = small
    shutil.copytree(out / "sessions", tmp_path / "sessions", ignore=shutil.ignore_patterns("*certificate*"))
    _clean_row_only(out, tmp_path)
    from skinlayers.calibration import pipeline

    monkeypatch.setattr(pipeline, "card_spectrum_flags", lambda *args: [])
    result = run_stability(tmp_path, plan=StabilityPlan({"certificate 430 nm": (-0.08,)}, ["gn-hom"], 16, seed=5), say=lambda s: None)
    silent = result.summary["methods"]["gn-hom"]["silent"]
    assert ("certificate 430 nm", "-0.08") in [(s["condition"], s["strength"]) for s in silent]


def test_a_wrong_certificate_is_recorded_at_its_band_only():
    from skinlayers.analyses.stability import _recorded_rig

    manifest = {"rig": _default_rig()}
    changed = _recorded_rig(manifest, "certificate 430 nm", -0.08)["rig"]["targets"]["spectralon_reflectance"]
    assert changed[430.0] == pytest.approx(0.99 * 0.92) and all(v == pytest.approx(0.99) for w, v in changed.items() if w != 430.0)
    every = _recorded_rig(manifest, "certificate all bands", -0.05)["rig"]["targets"]["spectralon_reflectance"]
    assert len(every) == 9 and all(v == pytest.approx(0.99 * 0.95) for v in every.values())
    assert manifest["rig"]["targets"]["spectralon_reflectance"] == 0.99  # the session's own record untouched


def _default_rig() -> dict:
    from skinlayers.acquire.hardware.rig import load_rig

    return load_rig().model_dump(mode="json")


def test_a_rerun_measures_only_the_missing_cells(small, tmp_path):
    out, _, _ = small
    shutil.copytree(out, tmp_path / "again")
    said: list[str] = []
    result = run_stability(tmp_path / "again", plan=StabilityPlan({**SMALL, "noise": (8.0, 0.25)}, ["gn-hom"], 16, seed=5), say=said.append)
    measured = [line for line in said if line.startswith("[")]
    assert len(measured) == 1 and "noise, 0.25" in measured[0]
    assert len(list(csv.DictReader(result.table.open()))) == 6


def test_another_seed_in_the_same_folder_is_measured_not_taken_from_the_table(small, tmp_path):
    out, _, _ = small
    shutil.copytree(out, tmp_path / "again")
    said: list[str] = []
    run_stability(tmp_path / "again", plan=StabilityPlan({"dead band": (550,)}, ["gn-hom"], 16, seed=6), say=said.append)
    assert len([line for line in said if line.startswith("[")]) == 2  # clean and the dead band, at seed 6


def test_the_same_seed_gives_the_same_cells_twice(small, tmp_path):
    """Seeded: the session simulated anew in another folder, fitted again, gives the same numbers."""
    out, _, _ = small
    result = run_stability(tmp_path, plan=StabilityPlan({"dead band": (550,)}, ["gn-hom"], 16, seed=5), say=lambda s: None)
    again = {(r["condition"], r["strength"]): r for r in csv.DictReader(result.table.open())}
    first = {(r["condition"], r["strength"]): r for r in csv.DictReader((out / "stability.csv").open())}
    assert set(again) == {("clean", ""), ("dead band", "550")}
    measured = [c for c in COLUMNS if c.startswith("error_") or c in ("residual_over_noise", "sigma_cover", "iterations", "message")]
    for key, row in again.items():
        assert {c: row[c] for c in measured} == {c: first[key][c] for c in measured}, key


def test_a_cell_coloured_by_its_worst_target_hair_flagged_pixels_included():
    from skinlayers.analyses.stability import TARGETS, names_cause
    from skinlayers.analyses.stability_charts import CellTargets, worst_ratio

    targets = CellTargets(TARGETS, RESIDUAL_AT_NOISE, SIGMA_COVER, names_cause)
    row = _row(sigma_cover_flagged="")
    assert worst_ratio(row, targets) == pytest.approx(max(0.5, 1.0 / RESIDUAL_AT_NOISE, SIGMA_COVER / 0.9))
    assert worst_ratio(_row(sigma_cover_flagged=SIGMA_COVER / 2), targets) == pytest.approx(2.0)


def test_bad_input_ends_in_one_line(run_cli, tmp_path):
    """A folder holding another analysis's table, a bad device: one line on stderr, status 1."""
    (tmp_path / "stability.csv").write_text("a,b\n1,2\n")
    for args, words in ((["-o", str(tmp_path)], "columns"), (["--device", "tpu", "-o", str(tmp_path / "n")], "--device")):
        code, out, err = run_cli("stability", "--quick", *args)
        assert code == 1 and err.startswith("error:") and words in err and "Traceback" not in err, (args, err)
        assert len(err.strip().splitlines()) == 1
