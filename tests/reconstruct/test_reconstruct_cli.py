"""``skinlayers reconstruct``: session or cube in, maps.exr + fit.json + report.png + settings out;
errors a user can cause end as one line and exit 1."""

from __future__ import annotations

import json

import pytest
import torch
import yaml
from typer.testing import CliRunner

from skinlayers.formats.cube import write_cube
from skinlayers.cli import app
from skinlayers.model import PARAMETER_NAMES
from skinlayers.formats.exr import read_exr
from skinlayers.model.patch.maps_io import read_maps
from skinlayers.reconstruct.choice.fidelity import CROSSTALK_LIMIT
from skinlayers.reconstruct.settings import FitSettings, FitSettingsError, load_fit_settings

runner = CliRunner()


@pytest.fixture(scope="module")
def session(tmp_path_factory, small_cube):
    """A session folder whose cube lies where ``skinlayers calibrate`` writes it: beside the session."""
    folder = tmp_path_factory.mktemp("sessions") / "arm"
    folder.mkdir()
    write_cube(folder.parent / "arm_calibrated" / "cube.exr", small_cube.cube)
    return folder


def _invoke(args):
    from skinlayers.cli import main  # noqa: F401 (the same app main() runs)

    return runner.invoke(app, args, catch_exceptions=True)


@pytest.fixture(scope="module")
def run(session, tmp_path_factory):
    config = tmp_path_factory.mktemp("config") / "fit.yaml"
    # changes flags only, so the maps must equal small_fit's (the same model: carotene per pixel)
    config.write_text("high_residual_factor: 3.5\nmap_cell_mm: {C_bc: 0}\n")
    result = _invoke(["reconstruct", str(session), "--config", str(config), "--device", "cpu"])
    return result, config


def test_second_run_from_the_cli_is_identical(run, session, small_fit):
    result, _ = run
    assert result.exit_code == 0, result.output
    maps = read_maps(session.parent / "arm_reconstruction" / "maps.exr")
    for n in PARAMETER_NAMES:
        assert torch.equal(getattr(maps, n), getattr(small_fit.maps, n)), n
    summary = json.loads((session.parent / "arm_reconstruction" / "fit.json").read_text())
    assert summary["scale"] == small_fit.scale


def test_reconstruct_a_session_writes_every_output(run, session):
    result, config = run
    assert result.exit_code == 0, result.output
    assert "threads: 1 thread(s): as asked (SKINLAYERS_THREADS=1)" in result.output  # the suite's policy
    out = session.parent / "arm_reconstruction"
    for name in ("maps.exr", "fit.json", "report.png", "fit_settings.yaml"):
        assert (out / name).exists(), name
    maps = read_maps(out / "maps.exr")  # the renderer's map format, validated
    assert maps.shape == (1, 24, 24)
    channels, header = read_exr(out / "maps.exr")
    wl = [430, 460, 490, 520, 550, 580, 610, 640, 670]
    expected = {"residual_rms", "flags", *(f"res_{w}" for w in wl), *(f"sigma_{n}" for n in PARAMETER_NAMES)}
    assert expected <= set(channels)
    assert json.loads(header["flag_bits"])["high_residual"] == 4
    summary = json.loads((out / "fit.json").read_text())
    for key in ("settings", "iterations", "time", "residual", "parameters", "correlations", "pca", "flags", "data_checks", "scale"):
        assert key in summary, key
    assert summary["settings"]["high_residual_factor"] == 3.5
    assert set(summary["parameters"]) == set(PARAMETER_NAMES)
    assert "p5" in summary["parameters"]["C_m"] and "p95" in summary["parameters"]["C_m"]
    assert summary["view_angle_source"] == "cube header"
    assert summary["band_fwhm_source"] == "cube header" and summary["band_fwhm_nm"] == [10.0] * 9
    assert abs(sum(summary["pca"]["explained_ratio"]) - 1.0) < 1e-9
    resolved = yaml.safe_load((out / "fit_settings.yaml").read_text())
    assert FitSettings.model_validate(resolved) == FitSettings(high_residual_factor=3.5, map_cell_mm={"C_bc": 0})
    assert summary["map_grids"]["C_bc"] == "pixel" and summary["map_grids"]["C_hd"] == "pixel"  # 24²: under two pixels
    assert summary["forward_choice"]["setting"] == "auto" and summary["forward_choice"]["chosen"] == "heterogeneous"
    assert summary["forward_choice"]["forecast"] > 2 * CROSSTALK_LIMIT and not summary["forward_choice"]["checks"]  # not tried
    assert [level["forward"] for level in summary["levels"]][-1] == "heterogeneous"
    assert "forward model: heterogeneous" in result.output
    assert "maps:" in result.output and "report:" in result.output
    # a second run into the same folder is refused unless forced
    again = _invoke(["reconstruct", str(session), "--config", str(config)])
    assert again.exit_code != 0 and "--force" in str(again.exception or again.output)


def test_session_folder_is_left_untouched(run, session):
    assert run[0].exit_code == 0
    assert list(session.iterdir()) == []


def test_a_calibrated_folder_or_cube_file_is_accepted(session, tmp_path):
    from skinlayers.reconstruct.cli import default_reconstruction_dir, resolve_cube_path

    calibrated = session.parent / "arm_calibrated"
    assert resolve_cube_path(session) == calibrated / "cube.exr"
    assert resolve_cube_path(calibrated) == calibrated / "cube.exr"
    assert resolve_cube_path(calibrated / "cube.exr") == calibrated / "cube.exr"
    assert default_reconstruction_dir(calibrated, calibrated / "cube.exr") == calibrated / "reconstruction"


def test_session_without_cube_says_to_calibrate(tmp_path):
    result = _invoke(["reconstruct", str(tmp_path)])
    assert result.exit_code != 0
    assert "skinlayers calibrate" in str(result.exception)


def test_bad_settings_name_the_key(tmp_path):
    bad = tmp_path / "fit.yaml"
    bad.write_text("method: simplex\n")
    with pytest.raises(FitSettingsError, match="method"):
        load_fit_settings(bad)
    bad.write_text("max_iteratons: 3\n")
    with pytest.raises(FitSettingsError, match="max_iteratons: unknown key"):
        load_fit_settings(bad)


def test_cli_errors_are_one_line(tmp_path, capsys, monkeypatch):
    import skinlayers.cli as cli

    monkeypatch.setattr("sys.argv", ["skinlayers", "reconstruct", str(tmp_path / "missing.exr")])
    with pytest.raises(SystemExit) as exit_info:
        cli.main()
    assert exit_info.value.code == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "missing.exr" in err and "\n" not in err


def test_model_choices_set_the_fit(session, tmp_path):
    """``--model paper`` is DWRR08's fit (the renderer, every map per pixel, a free scale), ``fixed`` the
    renderer on the settings' grids; an unknown choice is one line."""
    out = tmp_path / "paper"
    result = _invoke(["reconstruct", str(session), "--model", "paper", "-o", str(out), "--device", "cpu"])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "fit.json").read_text())
    assert summary["settings"]["forward"] == "heterogeneous" and summary["settings"]["free_scale"] is True
    assert set(summary["map_grids"].values()) == {"pixel"} and summary["forward_choice"] is None
    assert load_fit_settings(None, forward="heterogeneous").forward == "heterogeneous"
    bad = _invoke(["reconstruct", str(session), "--model", "best", "-o", str(tmp_path / "bad")])
    assert bad.exit_code != 0 and "--model 'best'" in str(bad.exception or bad.output)


def test_shipped_yaml_is_the_embedded_default():
    from skinlayers.configs import config_path

    assert load_fit_settings(config_path("fit.yaml")) == FitSettings()


def test_reconstruct_fits_an_envi_cube_to_the_maps_of_its_exr(tmp_path, small_cube, small_fit, run_cli):
    """The same cube as ENVI and as cube.exr: ``skinlayers reconstruct`` gives the same maps to the bit."""
    from skinlayers.formats.foreign.cubes import write_cube_file

    envi = write_cube_file(tmp_path / "arm.hdr", small_cube.cube)
    config = tmp_path / "fit.yaml"
    config.write_text("map_cell_mm: {C_bc: 0}\n")  # small_fit's settings
    code, out, err = run_cli("reconstruct", str(envi), "--config", str(config), "--device", "cpu", "-o", str(tmp_path / "rec"))
    assert code == 0, out + err
    maps = read_maps(tmp_path / "rec" / "maps.exr")
    for n in PARAMETER_NAMES:
        assert torch.equal(getattr(maps, n), getattr(small_fit.maps, n)), n
    assert json.loads((tmp_path / "rec" / "fit.json").read_text())["scale"] == small_fit.scale


def _drawn_texts(fig) -> list:
    """The texts the figure draws: its title, each shown axes' title, its tick labels, axis labels and
    offset texts where its axis is on (a colour bar's too), and the legends' entries."""
    texts = [fig._suptitle] if fig._suptitle is not None else []
    for ax in fig.axes:
        if not ax.get_visible():
            continue
        texts += [ax.title, ax._left_title, ax._right_title]
        if ax.axison:
            for axis in (ax.xaxis, ax.yaxis):
                texts += [t for t in axis.get_ticklabels() if t.get_visible()] + [axis.label, axis.offsetText]
        if ax.get_legend() is not None:
            texts += list(ax.get_legend().get_texts())
    return [t for t in texts if t.get_visible() and t.get_text().strip()]


def _overlaps(fig) -> list[tuple[str, str]]:
    """Pairs of drawn texts whose boxes overlap (by more than half a pixel each way)."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    boxes = [(t.get_text(), t.get_window_extent(renderer)) for t in _drawn_texts(fig)]
    pairs = []
    for i, (a, ba) in enumerate(boxes):
        for b, bb in boxes[i + 1:]:
            if min(ba.x1, bb.x1) - max(ba.x0, bb.x0) > 0.5 and min(ba.y1, bb.y1) - max(ba.y0, bb.y0) > 0.5:
                pairs.append((a[:40], b[:40]))
    return pairs


def test_the_report_has_no_overlapping_text_a_flag_legend_and_no_bar_for_a_patch_value(small_fit, small_cube):
    import matplotlib.pyplot as plt

    from skinlayers.reconstruct.results.report import draw_report

    fig = draw_report(small_fit, small_cube.cube.reflectance, {"C_bc": "at its bound"})
    try:
        assert _overlaps(fig) == []
        flags_ax = [ax for ax in fig.axes if ax.get_title().startswith("flags")][0]
        legend = flags_ax.get_legend()
        assert legend is not None and all("%" in t.get_text() or t.get_text() == "no flag" for t in legend.get_texts())
        carotene = [ax for ax in fig.axes if ax.get_title().startswith("carotene")][0]
        assert "undetermined" in carotene.get_title()
        assert not any(im.colorbar is not None for im in carotene.images)  # no colour bar claims a range
    finally:
        plt.close(fig)
