"""``skinlayers calibrate``, through the ``register`` function the top-level command mounts."""

from __future__ import annotations

import json

import pytest
import typer
from typer.testing import CliRunner

from skinlayers.formats.manifest import ManifestError
from skinlayers.calibration.cli import register
from skinlayers.calibration.settings import SettingsFileError


@pytest.fixture(scope="module")
def app():
    app = typer.Typer()
    register(app)
    app.command("noop", hidden=True)(lambda: None)  # a second command keeps `calibrate` a subcommand
    return app


def test_calibrate_json_and_table(app, synthetic_session, tmp_path):
    runner = CliRunner()
    out = tmp_path / "cube"
    result = runner.invoke(app, ["calibrate", str(synthetic_session.path), "-o", str(out), "--json", "--no-gray-card", "--no-align"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert [b["wavelength_nm"] for b in report["bands"]] == [430.0, 550.0, 670.0]
    assert all(b["flash_factor"] == 1.0 and b["alignment_shift_px"] == [0.0, 0.0] for b in report["bands"])
    assert "settings" not in report
    assert json.loads((out / "calibration.json").read_text())["settings"]["gray_card"] is False
    again = runner.invoke(app, ["calibrate", str(synthetic_session.path), "-o", str(out), "--force"])
    assert again.exit_code == 0, again.output
    assert "670" in again.stdout and "valid" in again.stdout and "contact_sheet.png" in again.stdout


def test_errors_are_one_line_exceptions(app, synthetic_session, tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["calibrate", str(tmp_path)])
    assert isinstance(result.exception, ManifestError) and "not a session folder" in str(result.exception)
    result = runner.invoke(app, ["calibrate", str(synthetic_session.path), "-o", str(tmp_path / "o"), "--gray-card-roi", "1,2,3"])
    assert isinstance(result.exception, SettingsFileError) and "x0,y0,x1,y1" in str(result.exception)
    bad = tmp_path / "bad.yaml"
    bad.write_text("gray_card: maybe\nunknown_key: 1\n")
    result = runner.invoke(app, ["calibrate", str(synthetic_session.path), "--config", str(bad)])
    message = str(result.exception)
    assert isinstance(result.exception, SettingsFileError) and "bad.yaml" in message and "unknown_key: unknown key" in message
    assert "\n" not in message
