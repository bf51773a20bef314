"""The transport reference from the command line: ``render`` and ``spectrum`` with ``--physics
transport``, and ``capture --sim --physics transport`` (a session whose skin the Monte Carlo rendered,
its noise recorded in the truth). The physics itself is tested in tests/model/test_transport_reference.py."""

from __future__ import annotations

import json

import pytest
import torch
import yaml

from skinlayers.formats.exr import read_exr, read_spectral
from skinlayers.model import TABLE2, ModelSettings, SkinParams
from skinlayers.model.transport import TransportRenderer


def test_render_by_transport_writes_the_image_and_its_standard_error(tmp_path, run_cli):
    maps = tmp_path / "maps.exr"
    assert run_cli("example-maps", str(maps), "--size", "8", "--mm-per-pixel", "0.1")[0] == 0
    code, out, err = run_cli("render", str(maps), "--physics", "transport", "--photons", "20000", "--bands", "560,650",
                             "--light", "window:0.8", "-o", str(tmp_path / "mc"), "--device", "cpu")
    assert code == 0, err
    image, wl, header = read_spectral(tmp_path / "mc.exr")
    se, se_wl, _ = read_spectral(tmp_path / "mc.exr", prefix="SE")
    assert image.shape == se.shape == (2, 8, 8) and wl.tolist() == se_wl.tolist() == [560.0, 650.0]
    assert header["physics"] == "transport" and header["photons_per_band"] == "20000" and header["seed"] == "0"
    assert bool((se > 0).all()) and bool((se < image).all())  # noisy, but each pixel known to better than itself
    assert 0.05 < float(image.mean()) < 1.0 and "Monte Carlo, 20,000 photons a band" in out


def test_render_by_diffusion_is_labelled_and_carries_no_standard_error(tmp_path, run_cli):
    maps = tmp_path / "maps.exr"
    run_cli("example-maps", str(maps), "--size", "8", "--mm-per-pixel", "0.1")
    assert run_cli("render", str(maps), "--bands", "560", "-o", str(tmp_path / "d"), "--device", "cpu")[0] == 0
    channels, header = read_exr(tmp_path / "d.exr")
    assert header["physics"] == "diffusion" and not any(name.startswith("SE_") for name in channels)


def test_spectrum_by_transport_is_the_references_totals_with_their_errors(run_cli):
    code, out, err = run_cli("spectrum", "--preset", "III interior", "--physics", "transport", "--photons", "8000",
                             "--wavelengths", "470,650", "--seed", "4", "--json")
    assert code == 0, err
    report = json.loads(out)
    expected = TransportRenderer(ModelSettings()).totals(SkinParams.from_mapping(TABLE2["III interior"]),
                                                         torch.tensor([470.0, 650.0]), photons=8000, seed=4)
    assert report["physics"] == "transport" and report["photons"] == 8000
    assert report["reflectance"] == expected.reflectance.tolist() and report["std_error"] == expected.std_error.tolist()
    assert all(0 < e < 0.1 * r for r, e in zip(report["reflectance"], report["std_error"]))
    assert "lab" in report  # two wavelengths or more: its colour too


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--physics", "mc"], "--physics 'mc'"),
        (["--physics", "transport", "--photons", "10"], "--photons 10"),
        (["--photons", "5000"], "--photons goes with --physics transport"),
    ],
)
def test_bad_physics_options_are_one_line_errors(args, needle, run_cli):
    code, _, err = run_cli("spectrum", "--wavelengths", "560", *args)
    assert code == 1 and needle in err and err.count("\n") == 1


#: The slow pipeline test's bound: the fit's median pixel residual within this many times the truth's
#: Monte Carlo noise (the fit follows the noise, it cannot fit a broken cube).
RESIDUAL_OVER_NOISE = 2.0

BANDS = [{"wavelength_nm": 460, "filter_position": 3, "iso": 200}, {"wavelength_nm": 580, "filter_position": 7, "iso": 400}]


def test_a_session_rendered_by_transport_records_its_physics_and_noise(tmp_path, run_cli):
    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump({"name": "small", "bands": BANDS, "geometry": {"cube_px": 32, "rectify_px": 160}}))
    sim = tmp_path / "sim.yaml"
    sim.write_text(yaml.safe_dump({"filters": {"wavelength_samples": 1}}))
    out = tmp_path / "session"
    code, stdout, err = run_cli("capture", "--sim", "--physics", "transport", "--photons", "20000", "--rig", str(rig),
                                "--sim-settings", str(sim), "--out", str(out), "--yes", "--sim-wheel-time", "0", "--device", "cpu")
    assert code == 0, err
    record = json.loads((out / "truth" / "simulation.json").read_text())
    physics = record["truth_physics"]
    assert physics["physics"] == "transport" and physics["photons_per_node"] == 20000 and set(physics["seconds_per_band"]) == {"460", "580"}
    truth, _, header = read_spectral(out / "truth" / "reflectance.exr")
    se, _, _ = read_spectral(out / "truth" / "reflectance.exr", prefix="SE")
    assert header["physics"] == "transport" and se.shape == truth.shape == (2, 32, 32)
    assert bool((se > 0).all()) and [round(v, 6) for v in physics["std_error_median_per_band"].values()] == [
        round(float(v.median()), 6) for v in se]
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["notes"]["truth_physics"] == "transport" and manifest["notes"]["truth_photons_per_node"] == 20000


def test_photons_without_transport_truth_are_refused(tmp_path, run_cli):
    code, _, err = run_cli("capture", "--sim", "--photons", "5000", "--yes", "--out", str(tmp_path / "s"))
    assert code == 1 and "--photons goes with --physics transport" in err and not (tmp_path / "s").exists()


@pytest.mark.slow
def test_a_transport_session_goes_through_calibration_and_the_fit(tmp_path, run_cli):
    """The whole pipeline on skin the fit's physics did not make: nine bands, a 32² cube, 20,000 photons
    per wavelength node (slow: about a minute on two cores)."""
    from skinlayers.acquire.hardware.rig import load_rig

    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump(load_rig(geometry={"cube_px": 32, "rectify_px": 128}).model_dump(mode="json")))
    session = tmp_path / "arm"
    code, _, err = run_cli("capture", "--sim", "--physics", "transport", "--photons", "20000", "--rig", str(rig), "-o", str(session),
                           "--yes", "--sim-wheel-time", "0", "--device", "cpu")
    assert code == 0, err
    code, _, err = run_cli("calibrate", str(session))
    assert code == 0, err
    code, _, err = run_cli("reconstruct", str(session), "--device", "cpu")
    assert code == 0, err
    from skinlayers.model.patch.maps_io import read_maps

    maps = read_maps(tmp_path / "arm_reconstruction" / "maps.exr")
    fit = json.loads((tmp_path / "arm_reconstruction" / "fit.json").read_text())
    assert maps.shape == (1, 32, 32) and all(bool(torch.isfinite(v).all()) for v in maps.params().values())
    truth = json.loads((session / "truth" / "simulation.json").read_text())["truth_physics"]
    assert truth["physics"] == "transport" and len(truth["seconds_per_band"]) == 9
    noise = max(truth["std_error_median_per_band"].values())
    assert fit["residual"]["pixel_rms_median"] < RESIDUAL_OVER_NOISE * noise, (fit["residual"], noise)


def test_the_demo_refuses_photons_without_transport_before_making_a_folder(tmp_path, run_cli):
    code, _, err = run_cli("demo", "--photons", "5000", "--out", str(tmp_path / "d"))
    assert code == 1 and "--photons goes with --physics transport" in err and not (tmp_path / "d").exists()
    code, _, err = run_cli("demo", "--physics", "mc", "--out", str(tmp_path / "d"))
    assert code == 1 and "--physics 'mc'" in err and not (tmp_path / "d").exists()
