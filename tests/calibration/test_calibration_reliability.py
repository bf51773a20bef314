"""Calibration under a hostile but ordinary user: two runs into one folder at once, a failure half-way
through writing, a truncated raw file. Each reproduces a defect found by probing the command."""

from __future__ import annotations

import sys

import pytest

from skinlayers.calibration import CalibrationSettings, calibrate_session
from skinlayers.formats.files import file_sha256
from skinlayers.formats.manifest import read_manifest, write_manifest


def test_a_second_calibration_into_the_same_folder_at_once_is_refused(session_copy, tmp_path):
    from skinlayers.formats.outputs import OutputError, claim_outputs

    out = tmp_path / "out"
    with claim_outputs(out, ["cube.exr", "contact_sheet.png", "calibration.json"]):  # the first run, still working
        with pytest.raises(OutputError, match="another run .* is writing here"):
            calibrate_session(session_copy.path, out)
    assert not (out / "cube.exr").exists()


def test_a_calibration_that_fails_while_writing_leaves_nothing_and_can_be_rerun(session_copy, tmp_path, monkeypatch):
    """Before: cube.exr and contact_sheet.png written, then the report failed, and the next run was
    refused as "already holds a calibration"."""
    import skinlayers.calibration.pipeline as pipeline

    def broken(*args, **kwargs):
        raise OSError(28, "No space left on device")

    out = tmp_path / "out"
    with monkeypatch.context() as mp:
        mp.setattr(pipeline, "atomic_write", broken)
        with pytest.raises(OSError, match="No space left"):
            calibrate_session(session_copy.path, out, CalibrationSettings(align_bands=False))
    assert not out.exists()
    result = calibrate_session(session_copy.path, out, CalibrationSettings(align_bands=False))
    assert sorted(p.name for p in out.iterdir()) == ["calibration.json", "contact_sheet.png", "cube.exr"]
    assert result.cube_path == out / "cube.exr"


def test_a_truncated_raw_gives_one_line_and_no_librarys_chatter(session_copy, tmp_path, capfd, monkeypatch):
    path = session_copy.path / "skin_550.dng"
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])
    manifest = read_manifest(session_copy.path)
    next(f for f in manifest.frames if f.file == path.name).sha256 = file_sha256(path)
    write_manifest(session_copy.path, manifest)
    from skinlayers.cli import main

    monkeypatch.setattr(sys, "argv", ["skinlayers", "calibrate", str(session_copy.path), "-o", str(tmp_path / "out")])
    with pytest.raises(SystemExit) as exit_:
        main()
    err = capfd.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert exit_.value.code == 1
    assert len(lines) == 1 and lines[0].startswith("error: ") and "skin_550.dng (skin frame, 550 nm): cannot decode" in lines[0], err
