"""``skinlayers design-bands``: the radiometry against the simulator's measured noise, the fit's band
Jacobian against finite differences, and the search on constructed cases whose optimum is known."""

from __future__ import annotations

import math

import pytest
import torch

#: RMS of (calibrated cube − truth) per band of the default rig (430–670 nm every 30 nm), measured on the
#: default simulated 256² session (tests/bench/test_bench_identifiability.py, CAMERA_NOISE): a truth the
#: design's noise model did not make (the simulator's photons through the calibration).
MEASURED_NOISE = (0.0043, 0.0034, 0.0033, 0.0031, 0.0032, 0.0036, 0.0049, 0.0078, 0.0155)
III_INTERIOR = (0.005364, 0.151566, 0.001441, 0.000081, 0.004674)  # C_m, β_m, C_he, C_bc, C_hd (DWRR08 Table 2)


def test_the_radiometry_chooses_the_rigs_isos_and_predicts_its_noise():
    from skinlayers.acquire.hardware.rig import load_rig
    from skinlayers.analyses.band_design import Filter, Radiometry, band_jacobian

    rig, radiometry = load_rig(), Radiometry()
    filters = [Filter(b.wavelength_nm, b.fwhm_nm) for b in rig.bands]
    assert [radiometry.iso(f) for f in filters] == [b.iso for b in rig.bands]  # the rig file's rule, reproduced
    band, _ = band_jacobian(torch.tensor([III_INTERIOR], dtype=torch.float64), filters)
    predicted = [float(radiometry.reflectance_sd(f, band[0, j])) for j, f in enumerate(filters)]
    ratios = [p / m for p, m in zip(predicted, MEASURED_NOISE)]
    assert all(0.8 <= r <= 1.2 for r in ratios), ratios


def test_the_band_jacobian_is_the_derivative_of_the_band_reflectance():
    from skinlayers.analyses.band_design import Filter, band_jacobian

    filters = [Filter(450.0, 10.0), Filter(560.0, 20.0), Filter(690.0, 10.0)]
    skins = torch.tensor([III_INTERIOR, (0.03, 0.6, 0.003, 0.0004, 0.01)], dtype=torch.float64)
    band, jac = band_jacobian(skins, filters)
    h = 1e-6
    for k in range(5):
        step = torch.zeros(5, dtype=torch.float64)
        step[k] = h
        up, down = skins.clone(), skins.clone()
        if k == 1:  # β_m absolute; the others in log
            up[:, 1] += h
            down[:, 1] -= h
        else:
            up[:, k] *= math.exp(h)
            down[:, k] *= math.exp(-h)
        numeric = (band_jacobian(up, filters)[0] - band_jacobian(down, filters)[0]) / (2 * h)
        assert torch.allclose(jac[..., k], numeric, rtol=1e-5, atol=1e-9), k


def _constructed_information() -> torch.Tensor:
    """Seven filters on one skin, every map per pixel: filters 1, 2, 3 and 4 each inform one scored map
    (C_m, β_m, C_he, C_hd) strongly; filters 0, 5 and 6 inform them all along one direction."""
    info = torch.zeros(7, 1, 5, 5, dtype=torch.float64)
    for f, k in ((1, 0), (2, 1), (3, 2), (4, 4)):
        info[f, 0, k, k] = 100.0
    for f in (0, 5, 6):
        v = torch.tensor([1.0, 1.0, 1.0, 0.0, 1.0], dtype=torch.float64)
        info[f, 0] = 60.0 * torch.outer(v, v)
    info[:, 0] += 1e-2 * torch.eye(5, dtype=torch.float64)
    return info


def test_the_search_finds_the_known_optimum():
    from skinlayers.analyses.band_design import Criterion, exchange_search, exhaustive_search

    info, per_pixel = _constructed_information(), torch.ones(5, dtype=torch.float64)
    for criterion in (Criterion(info, per_pixel, "targets"), Criterion(info, per_pixel, "rig", reference=[0, 5, 6])):
        assert exhaustive_search(criterion, 4).chosen == (1, 2, 3, 4)
        assert exchange_search(criterion, 4, starts=3).chosen == (1, 2, 3, 4)


def test_counting_up_by_exchange_finds_the_known_optimum(monkeypatch):
    """``search_counts`` by the exchange alone (the exhaustive limit set to nothing), two random starts: the
    known optimum of four, reached at five from the best four extended (a superset of the optimum)."""
    from skinlayers.analyses import band_design
    from skinlayers.analyses.band_design import Criterion, search_counts

    monkeypatch.setattr(band_design, "EXHAUSTIVE_LIMIT", 0)
    monkeypatch.setattr(band_design, "EXCHANGE_STARTS", 2)
    criterion = Criterion(_constructed_information(), torch.ones(5, dtype=torch.float64), "targets")
    found = search_counts(criterion, [4, 5])
    assert found[4].method == "exchange" and found[4].chosen == (1, 2, 3, 4)
    assert set(found[5].chosen) >= {1, 2, 3, 4} and found[5].score <= found[4].score


def test_the_exchange_agrees_with_the_exhaustive_search_on_random_catalogues():
    from skinlayers.analyses.band_design import Criterion, exchange_search, exhaustive_search

    generator = torch.Generator().manual_seed(3)
    shared = torch.tensor([1.0, 50.0, 1.0, 400.0, 8.0], dtype=torch.float64)
    for _ in range(3):
        vectors = torch.randn(10, 4, 5, 2, generator=generator, dtype=torch.float64)
        info = vectors @ vectors.transpose(-1, -2) + 1e-3 * torch.eye(5, dtype=torch.float64)
        criterion = Criterion(info, shared, "rig", reference=[0, 1, 2, 3])
        exact = exhaustive_search(criterion, 4)
        found = exchange_search(criterion, 4)
        assert found.chosen == exact.chosen and found.score == pytest.approx(exact.score)


def test_the_model_errors_bias_is_the_fits_least_squares_answer_to_it():
    """With the noise negligible, a set's expected error is the square of the unweighted least-squares fit
    of the linear model to the model's error alone (the fit weighs its bands alike)."""
    from skinlayers.analyses.band_information import Criterion, FilterTerms, _outer

    generator = torch.Generator().manual_seed(5)
    jac = torch.randn(2, 8, 5, generator=generator, dtype=torch.float64)  # (M, F, 5)
    error = 0.01 * torch.randn(2, 8, generator=generator, dtype=torch.float64)  # (M, F)
    terms = FilterTerms(_outer(jac * 1e8), _outer(jac), torch.einsum("mfi,mf->fmi", jac, error))
    chosen = [0, 2, 3, 5, 6, 7]
    variance = Criterion(terms, torch.ones(5, dtype=torch.float64), "targets").variance(chosen)[0]
    for m in range(2):
        answer = torch.linalg.lstsq(jac[m, chosen], error[m, chosen, None]).solution[:, 0]
        assert torch.allclose(variance[m], answer**2, rtol=1e-6, atol=1e-18)


def test_a_filter_the_model_misses_is_left_out():
    """Filters 1 and 7 inform C_m alike; the model misses what filter 1 sees (a bias): the search takes 7."""
    from skinlayers.analyses.band_design import exhaustive_search
    from skinlayers.analyses.band_information import Criterion, FilterTerms, _outer

    jac = torch.zeros(1, 8, 5, dtype=torch.float64)
    for f, k in ((1, 0), (2, 1), (3, 2), (4, 4), (7, 0)):
        jac[0, f, k] = 10.0
    for f in (0, 5, 6):
        jac[0, f] = math.sqrt(60.0) * torch.tensor([1.0, 1.0, 1.0, 0.0, 1.0], dtype=torch.float64)
    error = torch.zeros(1, 8, dtype=torch.float64)
    error[0, 1] = 0.5
    info = _outer(jac) + 1e-2 * torch.eye(5, dtype=torch.float64)
    terms = FilterTerms(info, _outer(jac), torch.einsum("mfi,mf->fmi", jac, error))
    assert exhaustive_search(Criterion(terms, torch.ones(5, dtype=torch.float64), "targets"), 4).chosen == (2, 3, 4, 7)


def test_the_model_error_is_measured_where_the_skin_varies_and_kept(tmp_path, monkeypatch):
    """The simulator's render against the fit's at the same maps: where blood absorbs (560 nm) the skin's
    variation within a pixel shows; at 700 nm little; the measurement is cached and read back."""
    from skinlayers.analyses import band_discrepancy
    from skinlayers.acquire.hardware.rig import load_rig
    from skinlayers.analyses.band_design import Filter

    monkeypatch.setenv("SKINLAYERS_CACHE", str(tmp_path))
    filters = [Filter(450.0, 10.0), Filter(560.0, 10.0), Filter(700.0, 10.0)]
    found = band_discrepancy.discrepancy(load_rig(), filters, cube_px=16)
    bias, spread = found.at(filters)
    assert found.cube_px == 16 and found.mm_per_pixel == pytest.approx(load_rig().geometry.window_mm / 16)
    assert bool(spread[1] > 3 * spread[2]) and bool((bias.abs() < 0.05).all()), (bias, spread)

    def refuse(*args, **kwargs):
        raise AssertionError("measured again")

    real, asked = band_discrepancy.measure_discrepancy, []

    def record(rig, wanted, **kwargs):
        asked.extend(wanted)
        return real(rig, wanted, **kwargs)

    monkeypatch.setattr(band_discrepancy, "measure_discrepancy", refuse)
    again = band_discrepancy.discrepancy(load_rig(), filters, cube_px=16)
    assert (again.bias_rel, again.spread_rel, again.seconds) == (found.bias_rel, found.spread_rel, 0.0)
    monkeypatch.setattr(band_discrepancy, "measure_discrepancy", record)
    more = band_discrepancy.discrepancy(load_rig(), [filters[1], Filter(560.0, 20.0)], cube_px=16)  # same centre, wider
    assert asked == [Filter(560.0, 20.0)] and more.bias_rel[0] == found.bias_rel[1]


def test_an_rgb_camera_cannot_determine_the_five_maps():
    """DWRR08 §6.1: five parameters a point, three channels. Under the same flash and noise model, the RGB
    camera leaves the maps it shares over cells undetermined (a uniform cell adds no new direction), while
    the rig's nine bands determine every map."""
    from skinlayers.analyses.band_information import (UNDETERMINED_SD, Criterion, Filter, Radiometry, filter_terms, joined_terms,
                                                      rgb_terms, shared_pixels)

    radiometry = Radiometry()
    skins = torch.tensor([III_INTERIOR, (0.03, 0.6, 0.003, 0.0004, 0.01)], dtype=torch.float64)
    rig = [Filter(b.wavelength_nm, b.fwhm_nm) for b in radiometry.rig.bands]
    terms = joined_terms(filter_terms(radiometry, skins, rig), rgb_terms(radiometry, skins, model_error=False))
    criterion = Criterion(terms, shared_pixels(radiometry.rig), "targets")
    rgb, nine = criterion.median_sd([9, 10, 11]), criterion.median_sd(list(range(9)))
    assert all(nine[k] < 1.0 for k in ("C_m", "beta_m", "C_he", "C_hd")), nine
    assert all(rgb[k] > UNDETERMINED_SD for k in ("beta_m", "C_bc", "C_hd")), rgb
    assert float(radiometry.rgb_sd(torch.full((1, 3), 0.5, dtype=torch.float64)).max()) < 0.02  # a plausible noise, not a blow-up


def test_the_shared_bound_is_the_inverse_of_the_whole_fisher_matrix():
    """n pixels of one skin, β_m, C_bc and C_hd shared by all: the variances equal the diagonal of the
    inverse of the n-pixel information matrix, built explicitly."""
    from skinlayers.analyses.band_design import bound_variance

    n = 6
    generator = torch.Generator().manual_seed(1)
    j = torch.randn(9, 5, generator=generator, dtype=torch.float64)
    fisher = j.T @ j
    per, shr = [0, 2], [1, 3, 4]
    whole = torch.zeros(2 * n + 3, 2 * n + 3, dtype=torch.float64)
    for i in range(n):
        a = slice(2 * i, 2 * i + 2)
        whole[a, a] = fisher[per][:, per]
        whole[a, 2 * n:] = fisher[per][:, shr]
        whole[2 * n:, a] = fisher[shr][:, per]
        whole[2 * n:, 2 * n:] += fisher[shr][:, shr]
    exact = torch.linalg.inv(whole).diagonal()
    shared = torch.tensor([1.0, n, 1.0, n, n], dtype=torch.float64)
    variance = bound_variance(fisher, shared)
    assert torch.allclose(variance[per], exact[:2], rtol=1e-9) and torch.allclose(variance[shr], exact[2 * n:], rtol=1e-9)


def test_the_nested_bound_is_the_inverse_of_the_whole_fisher_matrix():
    """Eight pixels of one skin: C_m and C_he per pixel, C_hd shared by pairs, β_m by fours, C_bc by all:
    the variances equal the diagonal of the inverse of the whole information matrix, built explicitly."""
    from skinlayers.analyses.band_design import bound_variance

    generator = torch.Generator().manual_seed(2)
    j = torch.randn(9, 5, generator=generator, dtype=torch.float64)
    fisher = j.T @ j
    counts = (1, 4, 1, 8, 2)  # C_m, β_m, C_he, C_bc, C_hd
    index, size = {}, 0
    for pixel in range(8):
        for k, n in enumerate(counts):
            key = (k, pixel // n)
            if key not in index:
                index[key], size = size, size + 1
    whole = torch.zeros(size, size, dtype=torch.float64)
    for pixel in range(8):
        rows = torch.tensor([index[(k, pixel // n)] for k, n in enumerate(counts)])
        whole[rows[:, None], rows] += fisher
    exact = torch.linalg.inv(whole).diagonal()
    variance = bound_variance(fisher, torch.tensor(counts, dtype=torch.float64))
    expected = torch.stack([exact[index[(k, 0)]] for k in range(5)])
    assert torch.allclose(variance, expected, rtol=1e-9)


@pytest.mark.parametrize("text, words", [
    ("centre,fwhm\n450,10\n", "centre_nm and fwhm_nm"),
    ("centre_nm,fwhm_nm\n450,ten\n", "line 2"),
    ("centre_nm,fwhm_nm\n900,10\n", "380–800"),
    ("centre_nm,fwhm_nm\n450,10\n450,20\n", "share a centre"),
])
def test_a_bad_catalogue_is_refused_naming_the_line(tmp_path, text, words):
    from skinlayers.analyses.band_design import read_catalogue
    from skinlayers.formats.errors import InputError

    path = tmp_path / "filters.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=words):
        read_catalogue(path)


def test_the_command_writes_a_rig_that_loads(tmp_path, run_cli):
    import json

    from skinlayers.acquire.hardware.rig import load_rig

    catalogue = tmp_path / "filters.csv"
    catalogue.write_text("centre_nm,fwhm_nm\n" + "".join(f"{c},10\n" for c in range(420, 660, 20)))  # 12 filters
    code, out, err = run_cli("design-bands", "--catalog", str(catalogue), "--count", "6", "--noise-only", "-o", str(tmp_path / "d"))
    assert code == 0, err
    record = json.loads((tmp_path / "d" / "design.json").read_text())
    assert record["search"]["method"] == "exhaustive" and record["search"]["sets_scored"] == 924  # 12 choose 6
    assert record["model_error"] is None
    assert len(record["chosen"]) == 6 and set(record["median_expected_sd"]) == {"chosen", "current rig", "evenly spaced", "RGB camera"}
    rig = load_rig(tmp_path / "d" / "rig.yaml")
    assert [b.wavelength_nm for b in rig.bands] == [f["centre_nm"] for f in record["chosen"]]
    assert [b.iso for b in rig.bands] == [f["iso"] for f in record["chosen"]] and (tmp_path / "d" / "bound_vs_count.png").is_file()
    code, _, err = run_cli("design-bands", "--count", "12", "-o", str(tmp_path / "e"))
    assert code == 1 and "--count 12" in err


def test_the_command_weighs_the_model_error_by_default(tmp_path, run_cli, monkeypatch):
    """The default path: the model's error (a stand-in marking one filter of the noise-only choice as badly
    modelled) enters the criterion, the record says so, and that filter is left out."""
    import json

    from skinlayers.analyses import band_discrepancy

    catalogue = tmp_path / "filters.csv"
    catalogue.write_text("centre_nm,fwhm_nm\n" + "".join(f"{c},10\n" for c in range(420, 660, 20)))  # 12 filters
    chosen = lambda folder: [f["centre_nm"] for f in json.loads((folder / "design.json").read_text())["chosen"]]  # noqa: E731
    code, _, err = run_cli("design-bands", "--catalog", str(catalogue), "--count", "6", "--noise-only", "-o", str(tmp_path / "e"))
    assert code == 0, err
    bad = chosen(tmp_path / "e")[2]

    def stand_in(rig, filters, **kwargs):
        bias = [-0.3 if f.centre_nm == bad else 0.0 for f in filters]
        return band_discrepancy.Discrepancy([f.centre_nm for f in filters], [f.fwhm_nm for f in filters], bias,
                                            [0.001] * len(filters), 0.1, 64, 20, 0.0)

    monkeypatch.setattr(band_discrepancy, "discrepancy", stand_in)
    code, _, err = run_cli("design-bands", "--catalog", str(catalogue), "--count", "6", "-o", str(tmp_path / "d"))
    assert code == 0, err
    record = json.loads((tmp_path / "d" / "design.json").read_text())
    assert record["model_error"]["cube_px"] == 64 and bad not in chosen(tmp_path / "d")


def test_a_design_is_not_written_over_an_earlier_one(tmp_path):
    from skinlayers.analyses.band_design import BandDesign, Filter, SearchResult, write_design
    from skinlayers.formats.outputs import OutputExistsError

    design = BandDesign([Filter(450.0, 10.0)], [200], "rig", SearchResult((0,), 0.9, "exhaustive", 1, 0.0),
                        {}, {"chosen": 0.9, "current rig": 1.0, "evenly spaced": 1.2}, {6: 1.0}, 0.0)
    write_design(design, tmp_path / "d")
    before = (tmp_path / "d" / "design.json").read_bytes()
    with pytest.raises(OutputExistsError):
        write_design(design, tmp_path / "d")
    assert (tmp_path / "d" / "design.json").read_bytes() == before
    write_design(design, tmp_path / "d", force=True)
