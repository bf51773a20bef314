"""The ``skinlayers`` command: outputs, and one clear line with a non-zero exit for bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest


NIST = Path(__file__).resolve().parent / "data" / "nist_skin_reflectance_forearm_avg_370-830nm.csv"




def test_spectrum_json(run_cli):
    code, out, _ = run_cli("spectrum", "--C_m", "0.02", "--beta_m", "0.5", "--C_he", "0.002",
                       "--C_bc", "0.001", "--C_hd", "0.005", "--wavelengths", "400:700:50", "--json")
    assert code == 0
    report = json.loads(out)
    assert report["wavelength_nm"] == [400, 450, 500, 550, 600, 650, 700]
    assert len(report["reflectance"]) == 7 and all(0 < r < 1 for r in report["reflectance"])
    assert len(report["srgb"]) == 3 and len(report["lab"]) == 3
    assert report["params"] == {"C_m": 0.02, "beta_m": 0.5, "C_he": 0.002, "C_bc": 0.001, "C_hd": 0.005}


def test_spectrum_comma_list_and_plot(tmp_path, run_cli):
    png = tmp_path / "s.png"
    code, out, _ = run_cli("spectrum", "--wavelengths", "450, 550,650", "--plot", str(png))
    assert code == 0 and png.stat().st_size > 10_000
    assert "sRGB" in out and "650" in out


def test_skin_types_figure(tmp_path, run_cli):
    png = tmp_path / "types.png"
    code, out, _ = run_cli("skin-types", "--plot", str(png), "--json")
    assert code == 0 and png.exists()
    rows = json.loads(out)["skin_types"]
    assert [r["name"] for r in rows][0] == "I interior" and len(rows) == 9


def test_fit_spectrum_json(tmp_path, run_cli):
    lines = NIST.read_text().splitlines()
    small = tmp_path / "three.csv"
    small.write_text("\n".join(",".join(line.split(",")[:4]) for line in lines if not line.startswith("#")) + "\n")
    code, out, _ = run_cli("fit-spectrum", str(small), "--json")
    assert code == 0
    report = json.loads(out)
    assert [s["name"] for s in report["spectra"]] == ["subject_1", "subject_2", "subject_3"]
    for s in report["spectra"]:
        assert set(s["params"]) == {"C_m", "beta_m", "C_he", "C_bc", "C_hd"}
        assert 0 < s["rms_residual"] < 0.06
        assert isinstance(s["at_bound"], list)
    assert report["summary"]["samples"] == 101
    assert report["summary"]["model"] == "auto" and sum(report["summary"]["chosen"].values()) == 3
    for s in report["spectra"]:  # the default weighs every candidate and says why the winner won
        model = s["model"]
        assert len(model["criterion"]) == 8 and model["why"]
        winner = min(model["criterion"], key=model["criterion"].get)
        assert winner == ("+".join(model["freed"]) or "fixed")
        assert s["rms_residual"] == pytest.approx(model["rms_residual"][winner])
        assert s["rms_residual"] <= model["rms_residual"]["fixed"]
    code, out, _ = run_cli("fit-spectrum", str(small), "--json", "--model", "fixed")
    fixed = json.loads(out)
    code, out, _ = run_cli("fit-spectrum", str(small), "--json", "--model", "fixed", "--method", "tables")
    assert code == 0
    tabulated = json.loads(out)
    assert tabulated["summary"]["method"] == "tables"
    for s, f, t in zip(report["spectra"], fixed["spectra"], tabulated["spectra"]):
        assert f["model"]["freed"] == [] and list(f["model"]["criterion"]) == ["fixed"]
        assert f["rms_residual"] == pytest.approx(s["model"]["rms_residual"]["fixed"], rel=1e-9)
        assert t["rms_residual"] == pytest.approx(f["rms_residual"], rel=0.01)
    chosen = tmp_path / "model.yaml"
    chosen.write_text("free: [dermis_scattering_ratio]\nfree_scale: true\n")
    code, out, _ = run_cli("fit-spectrum", str(small), "--json", "--model", str(chosen))
    assert code == 0
    from_file = json.loads(out)
    assert from_file["summary"]["free_scale"] and all(s["model"]["freed"] == ["dermis_scattering_ratio"]
                                                       for s in from_file["spectra"])


def test_fit_spectrum_with_transport_profiles_weighs_the_fixed_model_only(tmp_path, run_cli):
    """Transport's totals are tabulated at the settings' constants: ``auto`` has one candidate, and a
    model file that frees a constant is refused in one line."""
    lines = NIST.read_text().splitlines()
    small = tmp_path / "one.csv"
    small.write_text("\n".join(",".join(line.split(",")[:2]) for line in lines if not line.startswith("#")) + "\n")
    config = tmp_path / "transport.yaml"
    config.write_text("profiles: transport\n")
    code, out, _ = run_cli("fit-spectrum", str(small), "--json", "--config", str(config))
    assert code == 0
    entry = json.loads(out)["spectra"][0]
    assert list(entry["model"]["criterion"]) == ["fixed"] and entry["model"]["freed"] == []
    frees = tmp_path / "frees.yaml"
    frees.write_text("free: [oxygenation_dermis]\n")
    code, _, err = run_cli("fit-spectrum", str(small), "--config", str(config), "--model", str(frees))
    assert code == 1 and "needs profiles: diffusion" in err and err.count("\n") == 1


@pytest.mark.parametrize(
    "args, needle",
    [
        (["spectrum", "--C_m", "-0.1"], "C_m must be >= 0"),
        (["spectrum", "--C_m", "0.6", "--C_he", "0.3", "--C_bc", "0.2"], "C_m + C_he + C_bc must be <= 1"),
        (["spectrum", "--C_hd", "nan"], "C_hd must be a finite number"),
        (["spectrum", "--wavelengths", "700:400:5"], "--wavelengths"),
        (["spectrum", "--wavelengths", "300:500:10"], "380–800 nm"),
        (["spectrum", "--preset", "VII"], "--preset"),
        (["spectrum", "--illuminant", "D99"], "illuminant"),
        (["fit-spectrum", "/nonexistent/file.csv"], "cannot read"),
        (["fit-spectrum", str(NIST), "--range", "300:900"], "--range"),
        (["fit-spectrum", str(NIST), "--method", "fast"], "--method"),
        (["fit-spectrum", str(NIST), "--model", "best"], "--model 'best'"),
        (["fit-spectrum", str(NIST), "--noise", "0"], "--noise"),
    ],
)
def test_bad_input_one_clear_line(args, needle, run_cli):
    code, out, err = run_cli(*args)
    assert code != 0
    assert needle in err
    assert err.startswith("error: ") and err.count("\n") == 1
    assert "Traceback" not in err + out


def test_bad_files_one_clear_line(tmp_path, run_cli):
    params = tmp_path / "p.yaml"
    params.write_text("C_m: 0.01\nmelanin: 0.2\n")
    code, _, err = run_cli("spectrum", "--params", str(params))
    assert code == 1 and "unknown key(s) melanin" in err
    config = tmp_path / "c.yaml"
    config.write_text("optics:\n  n_epidermis: 1.4\n  colour: red\n")
    code, _, err = run_cli("spectrum", "--config", str(config))
    assert code == 1 and "optics.colour: unknown key" in err
    csv = tmp_path / "bad.csv"
    csv.write_text("wavelength_nm,a\n400,0.3\n410,NaN\n")
    code, _, err = run_cli("fit-spectrum", str(csv))
    assert code == 1 and "NaN" in err and "line 3" in err and err.count("\n") == 1


def test_console_script_runs(tmp_path):
    """The installed package in a fresh interpreter (outside the source tree): help works, bad input exits 1."""
    ok = subprocess.run([sys.executable, "-m", "skinlayers", "--help"], capture_output=True, text=True, timeout=120,
                        cwd=tmp_path)
    assert ok.returncode == 0 and "fit-spectrum" in ok.stdout
    bad = subprocess.run([sys.executable, "-m", "skinlayers", "spectrum", "--beta_m", "2"],
                         capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert bad.returncode == 1 and "beta_m must be <= 1" in bad.stderr and "Traceback" not in bad.stderr


def test_render_writes_spectral_exr_and_png(tmp_path, run_cli):
    maps = tmp_path / "maps.exr"
    code, _, _ = run_cli("example-maps", str(maps), "--size", "24", "--mm-per-pixel", "0.1")
    assert code == 0
    code, out, err = run_cli("render", str(maps), "--light", "window:1.6", "--bands", "450,550,650",
                         "--edit", "blood*1.5", "-o", str(tmp_path / "out" / "r"), "--device", "cpu")
    assert code == 0, err
    from skinlayers.formats.exr import read_spectral

    image, wl, header = read_spectral(tmp_path / "out" / "r.exr")
    assert image.shape == (3, 24, 24) and wl.tolist() == [450.0, 550.0, 650.0]
    assert float(image[:, 12, 12].min()) > 0.05 and float(image[:, 0, 0].max()) < float(image[:, 12, 12].min())
    assert (tmp_path / "out" / "r.png").stat().st_size > 500
    assert "rendered 24×24 px at 3 bands" in out


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--light", "laser"], "--light 'laser'"),
        (["--edit", "blood+2"], "NAME*FACTOR"),
        (["--swap", "blood"], "NAME=FILE.exr"),
        (["--device", "tpu"], "--device"),
    ],
)
def test_render_bad_options(tmp_path, extra, needle, run_cli):
    maps = tmp_path / "maps.exr"
    run_cli("example-maps", str(maps), "--size", "8", "--mm-per-pixel", "0.1")
    code, _, err = run_cli("render", str(maps), "-o", str(tmp_path / "x"), *extra)
    assert code == 1 and needle in err and err.count("\n") == 1


def test_render_refuses_a_bad_maps_file(tmp_path, run_cli):
    import numpy as np

    from skinlayers.formats.exr import write_exr

    bad = write_exr(tmp_path / "bad.exr", {"C_m": np.zeros((4, 4), np.float32)}, {"mm_per_pixel": 0.1})
    code, _, err = run_cli("render", str(bad), "-o", str(tmp_path / "x"))
    assert code == 1 and "missing channel(s) beta_m, C_he, C_bc, C_hd" in err and "Traceback" not in err


def test_a_bug_keeps_its_traceback_and_a_user_error_is_one_line(monkeypatch, run_cli):
    """Only the project's user errors (and OSError) become ``error: …`` with status 1: a KeyError, a
    ValueError from a bug, propagates with its traceback instead of being shown as the user's fault."""
    import skinlayers.model.cli as model_cli
    from skinlayers.formats.errors import InputError

    def broken(*args, **kwargs):
        raise KeyError("band_fwhm_nm")

    monkeypatch.setattr(model_cli, "_spectrum_report", broken)
    with pytest.raises(KeyError):
        run_cli("spectrum", "--json")

    def refused(*args, **kwargs):
        raise InputError("the value is not usable", file="x.yaml", key="optics.n_dermis")

    monkeypatch.setattr(model_cli, "_spectrum_report", refused)
    code, _, err = run_cli("spectrum", "--json")
    assert code == 1 and err.strip() == "error: x.yaml: optics.n_dermis: the value is not usable"


@pytest.mark.parametrize("args", [["--help"], ["calibrate", "--help"], ["reconstruct", "--help"], ["render", "--help"]])
def test_help_shows_no_type_placeholder_beside_a_switch(run_cli, monkeypatch, args):
    """A switch (``--force``, ``--no-align``, ``--help``) or a count (``-v``) takes no value: ``--help``
    shows none beside it, and still shows what an option with a value takes."""
    monkeypatch.setenv("COLUMNS", "160")
    code, out, _ = run_cli(*args)
    assert code == 0
    assert "<bool>" not in out and not any("<int>" in line for line in out.splitlines() if "--verbose" in line), out
    assert "<path>" in out or args == ["--help"], out
