"""The README's promises under a hostile but ordinary user: a session is never written to, nothing is
overwritten without --force, bad settings end in one line naming the file and key, and work that cannot
fit in memory is refused before it starts. Each test reproduces a defect found by probing the
commands (before these tests, every one of them failed: wrote, overwrote, hung or ended in a traceback).

Calibration's own probes (a second run at once, a failure half-way, a truncated raw's stderr) are in
``tests/calibration/test_calibration_reliability.py``.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from skinlayers.formats.cube import Cube, CubeHeader, write_cube
from skinlayers.model import TABLE2
from skinlayers.model.patch.maps import SkinMaps
from skinlayers.model.patch.maps_io import write_maps

BANDS = [430.0, 460.0, 490.0, 520.0, 550.0, 580.0]


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def session(tmp_path) -> Path:
    """A session folder (its manifest) with its calibrated cube beside it, as calibrate leaves them."""
    folder = tmp_path / "S"
    folder.mkdir()
    (folder / "manifest.json").write_text("{}")
    header = CubeHeader(wavelengths_nm=BANDS, band_fwhm_nm=[10.0] * 6, camera_angle_deg=30.0, mm_per_pixel=0.47)
    write_cube(tmp_path / "S_calibrated" / "cube.exr", Cube(torch.full((6, 16, 16), 0.4), torch.ones(16, 16, dtype=torch.bool), header))
    return folder


@pytest.fixture
def maps_file(tmp_path) -> Path:
    return write_maps(tmp_path / "maps.exr", SkinMaps.uniform(TABLE2["III interior"], (16, 16), 0.1))


def _one_line(err: str) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err


# ---- 1. a session folder is never written to ------------------------------------------------------------


def test_reconstruct_refuses_an_output_inside_the_session(session, run_cli):
    before = _tree(session)
    code, _, err = run_cli("reconstruct", str(session), "-o", str(session / "rec"))
    assert code == 1 and "inside the session" in err
    _one_line(err)
    assert _tree(session) == before and not (session / "rec").exists()


@pytest.mark.parametrize("command", ["render", "example-maps", "capture"])
def test_no_command_writes_into_a_session(session, maps_file, run_cli, command):
    before = _tree(session)
    args = {
        "render": ["render", str(maps_file), "-o", str(session / "out")],
        "example-maps": ["example-maps", str(session / "x.exr"), "--size", "16"],
        "capture": ["capture", "--sim", "--yes", "-o", str(session / "inner")],
    }[command]
    code, _, err = run_cli(*args)
    assert code == 1 and "inside the session" in err, err
    _one_line(err)
    assert _tree(session) == before


# ---- 2. nothing is overwritten without --force -------------------------------------------------------------


def test_reconstruct_does_not_replace_a_users_files(session, tmp_path, run_cli):
    out = tmp_path / "rec"
    out.mkdir()
    (out / "maps.exr").write_bytes(b"a user's maps")
    (out / "report.png").write_bytes(b"a user's figure")
    code, _, err = run_cli("reconstruct", str(session), "-o", str(out))
    assert code == 1 and "already holds maps.exr, report.png" in err and "--force" in err
    assert (out / "maps.exr").read_bytes() == b"a user's maps"


def test_render_and_example_maps_do_not_replace_files(maps_file, tmp_path, run_cli):
    (tmp_path / "out.exr").write_bytes(b"earlier")
    code, _, err = run_cli("render", str(maps_file), "-o", str(tmp_path / "out"), "--bands", "450,550")
    assert code == 1 and "out.exr" in err and "--force" in err
    assert (tmp_path / "out.exr").read_bytes() == b"earlier"
    code, _, err = run_cli("example-maps", str(maps_file), "--size", "16")
    assert code == 1 and "maps.exr" in err and "--force" in err
    code, _, _ = run_cli("render", str(maps_file), "-o", str(tmp_path / "out"), "--bands", "450,550", "--force")
    assert code == 0 and (tmp_path / "out.exr").read_bytes()[:4] == b"\x76\x2f\x31\x01"  # an OpenEXR file now


def test_two_runs_at_once_one_is_refused(tmp_path):
    from skinlayers.formats.outputs import OutputError, claim_outputs

    with claim_outputs(tmp_path / "out", ["a.txt"]) as staging:
        staging.path("a.txt").write_text("first")
        with pytest.raises(OutputError, match="another run .* is writing here"):
            with claim_outputs(tmp_path / "out", ["a.txt"]):
                pass
    assert (tmp_path / "out" / "a.txt").read_text() == "first"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["a.txt"]  # no lock, no staging left


def test_a_lock_left_by_a_killed_run_is_taken_over(tmp_path):
    from skinlayers.formats.outputs import claim_outputs

    folder = tmp_path / "out"
    folder.mkdir()
    dead = 2**22 + 12345  # above Linux's default pid_max: no such process
    (folder / ".skinlayers.lock").write_text(f"{os.uname().nodename} {dead}\n")
    (folder / ".staging-killed").mkdir()  # what the killed run was writing
    with claim_outputs(folder, ["a.txt"]) as staging:
        staging.path("a.txt").write_text("taken over")
    assert sorted(p.name for p in folder.iterdir()) == ["a.txt"] and (folder / "a.txt").read_text() == "taken over"


def test_a_failed_run_leaves_what_was_there(tmp_path):
    from skinlayers.formats.outputs import claim_outputs

    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "a.txt").write_text("before")
    with pytest.raises(RuntimeError):
        with claim_outputs(folder, ["a.txt", "b.txt"], force=True, marker="b.txt") as staging:
            staging.path("a.txt").write_text("half")
            raise RuntimeError("the work failed")
    assert (folder / "a.txt").read_text() == "before" and sorted(p.name for p in folder.iterdir()) == ["a.txt"]
    with pytest.raises(KeyboardInterrupt):
        with claim_outputs(tmp_path / "new" / "deeper", ["a.txt"]) as staging:
            raise KeyboardInterrupt
    assert not (tmp_path / "new").exists()  # the folders the claim made go again


def test_the_marker_goes_last(tmp_path):
    """With --force the old marker goes first and the new one comes last: a folder holding a marker
    always holds that run's products."""
    from skinlayers.formats.outputs import claim_outputs

    folder = tmp_path / "out"
    with claim_outputs(folder, ["data", "done"], marker="done") as staging:
        staging.path("data").write_text("1")
        staging.path("done").write_text("1")
    seen = []
    real_replace = os.replace

    def spy(src, dst):
        seen.append((Path(dst).name, (folder / "done").exists()))
        real_replace(src, dst)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(os, "replace", spy)
        with claim_outputs(folder, ["data", "done"], force=True, marker="done") as staging:
            staging.path("data").write_text("2")
            staging.path("done").write_text("2")
    assert seen == [("data", False), ("done", False)]
    assert (folder / "data").read_text() == "2" == (folder / "done").read_text()


# ---- 3. YAML that would never end ---------------------------------------------------------------------------


def _alias_bomb(key: str) -> str:
    lines = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    for k in range(1, 10):
        lines.append(f"a{k}: &a{k} [" + ", ".join([f"*a{k - 1}"] * 10) + "]")
    return "x:\n" + "\n".join("  " + line for line in lines) + f"\n{key} [*a9]\n"


@pytest.mark.parametrize(
    "command, key",
    [("reconstruct", "ftol:"), ("calibrate", "ftol:"), ("capture", "name:")],
)
def test_an_alias_bomb_is_refused_at_once(tmp_path, session, run_cli, command, key):
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(_alias_bomb(key))
    args = {"reconstruct": ["reconstruct", str(session), "-o", str(tmp_path / "r"), "--config", str(bomb)],
            "calibrate": ["calibrate", str(session), "-o", str(tmp_path / "c"), "--config", str(bomb)],
            "capture": ["capture", "--sim", "--yes", "-o", str(tmp_path / "s"), "--rig", str(bomb)]}[command]
    start = time.perf_counter()
    code, _, err = run_cli(*args)
    assert time.perf_counter() - start < 30  # a functional bound (the bomb ran for minutes), not a benchmark
    assert code == 1 and "values once its aliases are expanded" in err and str(bomb) in err
    _one_line(err)
    assert len(err) < 400


def test_a_huge_rejected_value_gives_a_short_message(tmp_path):
    from skinlayers.reconstruct.settings import FitSettingsError, load_fit_settings

    f = tmp_path / "fit.yaml"
    f.write_text("ftol: [" + ", ".join(["0.1"] * 50_000) + "]\n")
    with pytest.raises(FitSettingsError) as err:
        load_fit_settings(f)
    assert str(f) in str(err.value) and "ftol" in str(err.value) and len(str(err.value)) < 400


def test_a_non_utf8_settings_file_is_named(tmp_path, session, run_cli):
    f = tmp_path / "fit.yaml"
    f.write_bytes("ftol: 0.001 # réglé\n".encode("latin-1"))
    code, _, err = run_cli("reconstruct", str(session), "-o", str(tmp_path / "r"), "--config", str(f))
    assert code == 1 and str(f) in err and "UTF-8" in err
    _one_line(err)


# ---- 4. sizes that cannot fit -------------------------------------------------------------------------------


def test_render_refuses_what_cannot_fit_before_it_starts(maps_file, tmp_path, run_cli, monkeypatch):
    import skinlayers.formats.resources as resources

    monkeypatch.setattr(resources, "available_memory_bytes", lambda device=None: 2 << 20)
    code, _, err = run_cli("render", str(maps_file), "-o", str(tmp_path / "out"), "--light", "window")
    assert code == 1 and "needs about" in err and "available here" in err and "fewer bands" in err
    _one_line(err)
    assert not list(tmp_path.glob("out*"))


def test_render_in_band_groups_gives_the_same_image(maps_file, tmp_path, run_cli, monkeypatch):
    """Where all bands do not fit at once, render draws them a few at a time: the same image, every group
    taking the inter-scattering terms all bands at once would (``SkinRenderer.series_terms_for``)."""
    from skinlayers.formats.exr import read_spectral
    from skinlayers.model.render.renderer import SkinRenderer, render_bytes

    code, _, _ = run_cli("render", str(maps_file), "-o", str(tmp_path / "whole"), "--bands", "450,550,650", "--light", "window")
    assert code == 0
    import skinlayers.formats.resources as resources

    from skinlayers.model.render.tiles import _COMMAND_BYTES

    one_band = render_bytes(1, 1, 16, 16, math.ceil(5.0 / 0.1), weight_cache_mb=1536)
    budget = _COMMAND_BYTES + 1.5 * one_band  # one band's render beside what the command always holds, not two
    monkeypatch.setattr(resources, "available_memory_bytes", lambda device=None: int(budget / resources.USABLE_SHARE))
    calls = []
    original = SkinRenderer.render
    monkeypatch.setattr(SkinRenderer, "render", lambda self, maps, light, wl, **kw: calls.append(len(wl)) or original(self, maps, light, wl, **kw))
    code, out, _ = run_cli("render", str(maps_file), "-o", str(tmp_path / "grouped"), "--bands", "450,550,650", "--light", "window")
    assert code == 0, out
    assert calls == [1, 1, 1]  # the bands did render one at a time
    whole, _, _ = read_spectral(tmp_path / "whole.exr")
    grouped, _, _ = read_spectral(tmp_path / "grouped.exr")
    assert torch.equal(whole, grouped)


def test_a_pixel_size_no_optics_resolves_is_refused(tmp_path, run_cli):
    from skinlayers.formats.exr import write_exr

    channels = {n: np.full((4, 4), v, np.float32) for n, v in TABLE2["III interior"].items()}
    tiny = write_exr(tmp_path / "tiny.exr", channels, {"mm_per_pixel": 1e-9})
    code, _, err = run_cli("render", str(tiny), "-o", str(tmp_path / "out"))
    assert code == 1 and "mm_per_pixel" in err
    _one_line(err)


def test_a_rig_asking_for_a_giant_cube_is_refused(tmp_path, run_cli):
    import yaml

    from skinlayers.acquire.hardware.rig import default_rig_path

    data = yaml.safe_load(default_rig_path().read_text())
    data["geometry"]["cube_px"] = 100_000
    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump(data))
    code, _, err = run_cli("capture", "--sim", "--yes", "-o", str(tmp_path / "s"), "--rig", str(rig))
    assert code == 1 and "geometry.cube_px" in err and str(rig) in err
    _one_line(err)


def test_the_fit_refuses_a_cube_that_cannot_fit(session, monkeypatch):
    import skinlayers.formats.resources as resources
    from skinlayers.formats.cube import read_cube
    from skinlayers.formats.resources import ResourceError
    from skinlayers.reconstruct import FitSettings, fit_cube

    monkeypatch.setattr(resources, "available_memory_bytes", lambda device=None: 1 << 20)
    with pytest.raises(ResourceError, match="fitting a 16×16 cube at 6 bands needs about"):
        fit_cube(read_cube(session.parent / "S_calibrated" / "cube.exr"), FitSettings())


def test_many_spectra_are_fitted_in_chunks_with_the_same_result():
    from skinlayers.model import SkinModel
    from skinlayers.reconstruct import fit_spectra

    wl = torch.linspace(420.0, 680.0, 14, dtype=torch.float64)
    model = SkinModel()
    truth = [TABLE2[k] for k in ("I interior", "III interior", "IV exterior", "V exterior", "II interior")]
    from skinlayers.model import SkinParams

    spectra = torch.stack([model.diffuse_reflectance(SkinParams.from_mapping(t), wl) for t in truth])
    whole = fit_spectra(spectra, wl, model)
    seen = []
    chunked = fit_spectra(spectra, wl, model, chunk=2, progress=lambda done, total: seen.append((done, total)))
    assert seen == [(2, 5), (4, 5), (5, 5)]
    assert torch.allclose(whole.params.as_tensor(), chunked.params.as_tensor(), rtol=1e-6, atol=1e-9)
    assert whole.at_bound == chunked.at_bound


# ---- 5. numbers that are not numbers ------------------------------------------------------------------------


@pytest.mark.parametrize(
    "command, text, key",
    [
        ("reconstruct", "border_mm: .inf\n", "border_mm"),
        ("capture-scene", "extent_mm: .inf\n", "extent_mm"),
        ("capture-rig", "targets: {spectralon_reflectance: .inf}\n", "spectralon_reflectance"),
        ("capture-rig", "targets: {spectralon_reflectance: .nan}\n", "spectralon_reflectance"),
        ("calibrate", "max_alignment_px: .inf\n", "max_alignment_px"),
    ],
)
def test_infinite_and_nan_values_are_refused_with_their_key(tmp_path, session, run_cli, command, text, key):
    f = tmp_path / "settings.yaml"
    f.write_text(text)
    args = {
        "reconstruct": ["reconstruct", str(session), "-o", str(tmp_path / "r"), "--config", str(f)],
        "calibrate": ["calibrate", str(session), "-o", str(tmp_path / "c"), "--config", str(f)],
        "capture-scene": ["capture", "--sim", "--yes", "-o", str(tmp_path / "s"), "--scene", str(f)],
        "capture-rig": ["capture", "--sim", "--yes", "-o", str(tmp_path / "s"), "--rig", str(f)],
    }[command]
    code, _, err = run_cli(*args)
    assert code == 1 and key in err and str(f) in err, err
    _one_line(err)


# ---- 7. the rest --------------------------------------------------------------------------------------------


def test_an_output_that_cannot_be_written_is_refused_before_the_work(session, tmp_path, run_cli, maps_file):
    a_file = tmp_path / "a_file"
    a_file.write_text("not a folder")
    code, _, err = run_cli("reconstruct", str(session), "-o", str(a_file))
    assert code == 1 and "is not a folder" in err
    _one_line(err)
    code, _, err = run_cli("render", str(maps_file), "-o", "/proc/skinlayers/out")
    assert code == 1 and "cannot be written" in err
    _one_line(err)


def test_every_output_file_is_readable_by_all(maps_file, tmp_path, run_cli):
    code, _, _ = run_cli("render", str(maps_file), "-o", str(tmp_path / "out"), "--bands", "450,550")
    assert code == 0
    for name in ("out.exr", "out.png"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o644, name
    assert maps_file.stat().st_mode & 0o777 == 0o644


@pytest.mark.parametrize("text", ["400:700:1e-9", "400:inf:5", "nan,500"])
def test_wavelength_lists_are_bounded_and_finite(run_cli, text):
    code, _, err = run_cli("spectrum", "--wavelengths", text, "--json")
    assert code == 1 and "--wavelengths" in err
    _one_line(err)


def test_a_simulated_rig_too_large_to_render_is_refused_before_the_session(tmp_path, run_cli, monkeypatch):
    import skinlayers.formats.resources as resources

    monkeypatch.setattr(resources, "available_memory_bytes", lambda device=None: 50 << 20)
    code, _, err = run_cli("capture", "--sim", "--yes", "-o", str(tmp_path / "s"))
    assert code == 1 and "simulating a" in err and "truth grid" in err
    _one_line(err)
    assert not (tmp_path / "s").exists()


def test_an_oversized_manifest_is_refused(tmp_path):
    from skinlayers.formats.manifest import MAX_MANIFEST_BYTES, ManifestError, read_manifest

    (tmp_path / "manifest.json").write_bytes(b" " * (MAX_MANIFEST_BYTES + 1))
    with pytest.raises(ManifestError, match="larger than"):
        read_manifest(tmp_path)
