"""Every reader fuzzed (issue 45): whatever a file or an instrument says, a reader either returns what
it read or raises the toolkit's one-line error naming the file (``SkinlayersError``; ``OSError`` for
what the system refuses) — never another exception, never a hang.

The default suite runs a short pass of every reader (15 generated cases each); the long pass sets
``SKINLAYERS_FUZZ_EXAMPLES=2000`` (docs/limits.md). Cases that once failed are kept as named
regression tests (``test_yaml_cases_that_break_parsers`` and below).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from skinlayers.acquire.hardware.fw102c import FW102C
from skinlayers.acquire.hardware.gphoto import parse_aperture_f, parse_shutter_s
from skinlayers.acquire.hardware.rig import load_rig
from skinlayers.acquire.simulator.scene import load_scene
from skinlayers.acquire.simulator.simulation_settings import load_simulation_settings
from skinlayers.calibration.settings import load_calibration_settings
from skinlayers.formats.cube import read_cube
from skinlayers.formats.errors import SkinlayersError
from skinlayers.formats.exr import read_spectral, write_exr
from skinlayers.formats.manifest import read_manifest
from skinlayers.model.patch.maps_io import read_maps
from skinlayers.model.settings import load_model_settings
from skinlayers.reconstruct.settings import load_fit_settings
from skinlayers.reconstruct.spectrum.spectra_io import read_spectra_csv

FUZZ_EXAMPLES = int(os.environ.get("SKINLAYERS_FUZZ_EXAMPLES", "15"))
#: A case may take at most this long (ms): a reader that hangs fails here.
DEADLINE_MS = 10_000
ALLOWED = (SkinlayersError, OSError)

YAML_LOADERS = {
    "rig": load_rig, "scene": load_scene, "simulation": load_simulation_settings,
    "calibration": load_calibration_settings, "fit": load_fit_settings, "model": load_model_settings,
}
EXR_READERS = {"cube": read_cube, "maps": read_maps, "spectral": lambda p: read_spectral(p)}


def _short(examples: int):
    return settings(max_examples=examples, deadline=DEADLINE_MS, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                           HealthCheck.data_too_large])


def _refuses_cleanly(read, path: Path) -> None:
    """``read(path)`` returns, or raises an allowed error naming the file on what the CLI makes one line."""
    try:
        read(path)
    except ALLOWED as exc:
        message = " ".join(str(exc).split())
        assert message and (path.name in message or str(path.parent) in message), f"{type(exc).__name__}: {message}"


# -- values that break readers ----------------------------------------------------------------------
scalars = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(10**30), max_value=10**30),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=30),
    st.sampled_from(["nan", ".inf", "-.inf", "1e400", "0x1F", "~", "yes", "null", "é\u202e", "\x00"]),
)
nested = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(st.text(max_size=12), inner, max_size=4)),
                      max_leaves=20)


def _mutations(keys: list[str]):
    """A settings-like mapping: the file's own keys with fuzzed values, plus keys of its own."""
    return st.dictionaries(st.sampled_from(keys) | st.text(max_size=12), nested, max_size=6)


YAML_KEYS = ["bands", "camera", "wheel", "geometry", "base", "hairs", "scar", "sensor", "flash", "truth",
             "method", "max_iterations", "map_cell_mm", "forward", "render", "optics", "tables", "profiles",
             "gray_card", "flat_field", "interpolation", "align_border", "extent_mm", "wavelength_nm", "iso"]


def _yaml_pass(tmp_path: Path, loader: str, content: dict | str) -> None:
    path = tmp_path / f"{loader}.yaml"
    text = content if isinstance(content, str) else yaml.safe_dump(content, allow_unicode=True)
    path.write_text(text, encoding="utf-8")
    _refuses_cleanly(YAML_LOADERS[loader], path)


@pytest.mark.parametrize("loader", sorted(YAML_LOADERS))
@_short(FUZZ_EXAMPLES)
@given(data=st.data())
def test_yaml_settings(tmp_path, loader, data):
    _yaml_pass(tmp_path, loader, data.draw(_mutations(YAML_KEYS)))


@pytest.mark.parametrize("text", [
    "a: &x [*x]\n",                                    # an alias to itself
    "bands: &b [*b, *b]\n",
    "x: !!python/object:os.system ['true']\n",         # a tag safe_load refuses
    "- 1\n- 2\n",                                      # not a mapping
    "bands: [{wavelength_nm: .nan}]\n",
    "max_iterations: 1e999\n",
    "{" * 500 + "}" * 500 + "\n",                      # deep nesting
    "key: value\n" * 20000,                            # a large file
    "\ufeffmethod: gn\n",
    "method: \"\\ud800\"\n",
])
@pytest.mark.parametrize("loader", ["rig", "fit"])
def test_yaml_cases_that_break_parsers(tmp_path, loader, text):
    _yaml_pass(tmp_path, loader, text)


# -- EXR ----------------------------------------------------------------------------------------------
CHANNEL_NAMES = ["R_430", "R_460", "R_nan", "mask", "C_m", "beta_m", "C_he", "C_bc", "C_hd", "rho_s", "P_500",
                 "sigma_C_m", "R_", "R_1e999", "SE_430"]
pixel_values = st.sampled_from([0.0, 0.5, 1.0, -1.0, float("nan"), float("inf"), 1e30, 2.0])


@st.composite
def exr_files(draw):
    h, w = draw(st.integers(1, 6)), draw(st.integers(1, 6))
    names = draw(st.lists(st.sampled_from(CHANNEL_NAMES) | st.text(min_size=1, max_size=8), min_size=1, max_size=7,
                          unique=True))
    channels = {n: np.full((h, w), draw(pixel_values), np.float32) for n in names}
    attributes = draw(st.dictionaries(st.sampled_from(["wavelengths_nm", "mm_per_pixel", "cube_version", "bands"]),
                                      st.one_of(st.floats(allow_nan=True), st.lists(st.floats(), max_size=4),
                                                st.text(max_size=6)), max_size=3))
    return channels, attributes


@pytest.mark.parametrize("reader", sorted(EXR_READERS))
@_short(FUZZ_EXAMPLES)
@given(case=exr_files())
def test_exr_contents(tmp_path, reader, case):
    channels, attributes = case
    path = tmp_path / "f.exr"
    try:
        write_exr(path, channels, attributes)
    except (ValueError, TypeError, RuntimeError):
        return  # OpenEXR cannot store it: no file to read
    _refuses_cleanly(EXR_READERS[reader], path)


@pytest.fixture(scope="module")
def valid_exr(tmp_path_factory) -> bytes:
    path = tmp_path_factory.mktemp("exr") / "cube.exr"
    write_exr(path, {"R_430": np.full((8, 8), 0.4, np.float32), "R_560": np.full((8, 8), 0.5, np.float32),
                     "mask": np.ones((8, 8), np.float32)}, {"wavelengths_nm": [430.0, 560.0], "mm_per_pixel": 0.1})
    return path.read_bytes()


def _damaged(data: bytes, draw) -> bytes:
    """``data`` truncated, with bytes overwritten, or with bytes inserted."""
    kind = draw(st.sampled_from(["truncate", "overwrite", "insert"]))
    at = draw(st.integers(0, max(len(data) - 1, 0)))
    if kind == "truncate":
        return data[:at]
    junk = draw(st.binary(min_size=1, max_size=16))
    if kind == "overwrite":
        return data[:at] + junk + data[at + len(junk):]
    return data[:at] + junk + data[at:]


@pytest.mark.parametrize("reader", sorted(EXR_READERS))
@_short(FUZZ_EXAMPLES)
@given(data=st.data())
def test_exr_damaged_bytes(tmp_path, valid_exr, reader, data):
    path = tmp_path / "damaged.exr"
    path.write_bytes(_damaged(valid_exr, data.draw))
    _refuses_cleanly(EXR_READERS[reader], path)


# -- DNG / raw ----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def valid_dng(tmp_path_factory) -> bytes:
    from skinlayers.acquire.hardware.dng import write_dng

    raw = (np.arange(16 * 24, dtype=np.uint16).reshape(16, 24) * 7) % 4000
    path = write_dng(tmp_path_factory.mktemp("dng") / "frame.dng", raw, bits=12, black_level=[64] * 4, white_level=4095)
    return Path(path).read_bytes()


@_short(FUZZ_EXAMPLES)
@given(data=st.data())
def test_raw_damaged_or_foreign_bytes(tmp_path, valid_dng, data):
    from skinlayers.calibration.raw import read_raw

    path = tmp_path / "frame.dng"
    foreign = data.draw(st.sampled_from([b"", b"II*\x00", b"MM\x00*", b"\x89PNG\r\n\x1a\n", None]))
    path.write_bytes(_damaged(valid_dng, data.draw) if foreign is None else foreign + data.draw(st.binary(max_size=64)))
    _refuses_cleanly(read_raw, path)


# -- manifest.json --------------------------------------------------------------------------------------
MANIFEST_KEYS = ["format_version", "status", "frames", "rig", "created", "software", "subject", "site", "operator",
                 "simulated", "role", "band_nm", "file", "sha256", "exposure", "filter_position"]


@_short(FUZZ_EXAMPLES)
@given(data=st.data())
def test_manifest_json(tmp_path, data):
    session = tmp_path / "session"
    session.mkdir(exist_ok=True)
    kind = data.draw(st.sampled_from(["json", "text", "deep"]))
    if kind == "json":
        text = json.dumps(data.draw(_mutations(MANIFEST_KEYS)), allow_nan=True)
    elif kind == "deep":
        depth = data.draw(st.integers(100, 5000))
        text = "[" * depth + "]" * depth
    else:
        text = data.draw(st.text(max_size=200))
    (session / "manifest.json").write_text(text, encoding="utf-8", errors="surrogatepass")
    _refuses_cleanly(lambda p: read_manifest(p.parent), session / "manifest.json")


# -- CSV spectra ------------------------------------------------------------------------------------------
cells = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers(-5, 2000).map(str),
                  st.text(max_size=6), st.just(""))


@_short(FUZZ_EXAMPLES)
@given(rows=st.lists(st.lists(cells, min_size=0, max_size=8), max_size=12), header=st.booleans())
def test_spectra_csv(tmp_path, rows, header):
    path = tmp_path / "spectra.csv"
    lines = (["wavelength_nm,a,b"] if header else []) + [",".join(r) for r in rows]
    path.write_text("\n".join(lines), encoding="utf-8", errors="surrogatepass")
    _refuses_cleanly(read_spectra_csv, path)


def test_spectra_csv_with_a_hundred_thousand_columns(tmp_path):
    path = tmp_path / "wide.csv"
    path.write_text("wavelength_nm," + ",".join(f"s{i}" for i in range(100_000)) + "\n500," + ",".join(["0.5"] * 100_000) + "\n")
    _refuses_cleanly(read_spectra_csv, path)


# -- the filter wheel's serial replies --------------------------------------------------------------------
class _Garbage:
    """Serial-like: every write is answered with the next of ``replies`` (bytes; b"" is silence)."""

    def __init__(self, replies: list[bytes]) -> None:
        self.replies, self.pending, self.timeout, self.port = list(replies), bytearray(), None, "/dev/ttyFUZZ"

    def write(self, data: bytes) -> int:
        if self.replies:
            self.pending += self.replies.pop(0)
        return len(data)

    def read(self, size: int = 1) -> bytes:
        out = bytes(self.pending[:size])
        del self.pending[:size]
        return out

    def flush(self) -> None: ...

    def reset_input_buffer(self) -> None: ...

    def close(self) -> None: ...


replies = st.one_of(st.binary(max_size=40), st.builds(lambda c, a, p: c + b"\r" + a + p,
                                                       st.sampled_from([b"*idn?", b"pos?", b"pcount?", b"pos=3"]),
                                                       st.binary(max_size=12), st.sampled_from([b"> ", b">", b""])))


@_short(FUZZ_EXAMPLES)
@given(answers=st.lists(replies, max_size=8), action=st.sampled_from(["identify", "position", "move"]))
def test_wheel_serial_replies(answers, action):
    wheel = FW102C(_Garbage(answers), timeout_s=0.005, move_timeout_s=0.01, retries=1)
    try:
        {"identify": wheel.identify, "position": wheel.position, "move": lambda: wheel.move_to(3)}[action]()
    except ALLOWED as exc:
        assert "/dev/ttyFUZZ" in str(exc), exc


# -- the camera's gphoto2 output ---------------------------------------------------------------------------
@_short(FUZZ_EXAMPLES)
@given(text=st.text(max_size=40) | st.sampled_from(["1/0", "0/0", "1e999", "bulb", "f/nan", "-1/3", "1/ 250"]))
def test_gphoto_values(text):
    for parse in (parse_shutter_s, parse_aperture_f):
        value = parse(text)
        assert value is None or (isinstance(value, float) and value == value), (parse.__name__, text, value)


@_short(FUZZ_EXAMPLES)
@given(out=st.text(max_size=300))
def test_gphoto_auto_detect_output(monkeypatch, out):
    from skinlayers.acquire.hardware import gphoto

    monkeypatch.setattr(gphoto, "_run_gphoto2", lambda *a, **k: out)
    found = gphoto.detect_cameras()
    assert all(isinstance(m, str) and isinstance(p, str) for m, p in found)


def test_a_manifest_nested_thousands_deep_is_refused_in_one_line(tmp_path):
    """Found by the fuzzing: json's decoder recursed out of the stack (a RecursionError traceback)."""
    (tmp_path / "manifest.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(SkinlayersError, match="nested too deeply"):
        read_manifest(tmp_path)


def test_a_settings_file_nested_thousands_deep_is_refused_in_one_line(tmp_path):
    """Found by the fuzzing: PyYAML's parser recursed out of the stack (a RecursionError traceback)."""
    path = tmp_path / "fit.yaml"
    path.write_text("{" * 5000 + "}" * 5000 + "\n")
    with pytest.raises(SkinlayersError, match="nested more than"):
        load_fit_settings(path)


def test_a_cube_channel_named_r_nan_is_refused_in_one_line(tmp_path):
    """Found by the long fuzz pass: ``R_nan`` parsed as a wavelength of NaN, then no band was left to
    stack (a RuntimeError traceback)."""
    path = tmp_path / "cube.exr"
    write_exr(path, {"R_nan": np.zeros((1, 1), np.float32), "mask": np.zeros((1, 1), np.float32)})
    with pytest.raises(SkinlayersError, match="R_nan is not R_<nm>"):
        read_cube(path)


def test_a_header_attribute_that_cannot_even_print_is_refused_in_one_line(tmp_path):
    """Found by the long fuzz pass: a damaged cube's attribute of unknown type, whose repr fails to
    decode its bytes, turned the refusal itself into a UnicodeDecodeError traceback."""
    from skinlayers.formats.exr import float_attribute

    class Damaged:
        def __float__(self):
            raise TypeError("opaque")

        def __repr__(self):
            return b"\x80".decode()

    with pytest.raises(SkinlayersError, match="must be a number, got an unreadable Damaged"):
        float_attribute({"mm_per_pixel": Damaged()}, "mm_per_pixel", tmp_path / "cube.exr", SkinlayersError)
