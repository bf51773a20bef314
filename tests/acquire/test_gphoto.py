"""GPhotoCamera against a fake ``gphoto2`` program put first on PATH."""

from __future__ import annotations

import json
import os
import sys
import textwrap
from pathlib import Path

import pytest

from skinlayers.acquire.hardware.devices import Camera, CameraError, ExposureSettings
from skinlayers.acquire.hardware.gphoto import (
    GPhotoCamera,
    detect_cameras,
    format_shutter_s,
    parse_aperture_f,
    parse_shutter_s,
)
from skinlayers.acquire.hardware.rig import CameraConfig

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="the fake gphoto2 is a POSIX script")

# The fake prints what gphoto2 2.5 prints (actions.c: auto_detect_action, get_config_action) and keeps
# its camera's settings in a JSON state file between calls; every call is logged with its locale.
FAKE_GPHOTO2 = r'''
import json, os, sys, time
state_path = os.environ["FAKE_GPHOTO2_STATE"]
state = json.load(open(state_path))
args = sys.argv[1:]
with open(state_path + ".log", "a") as log:
    log.write(json.dumps({"args": args, "lc_all": os.environ.get("LC_ALL")}) + "\n")
def error(msg):
    sys.stderr.write("\n*** Error ***              \n" + msg + "\n")
    sys.exit(1)
if state.get("hang"):
    time.sleep(30)
opts = {}
i = 0
while i < len(args):
    if args[i] in ("--camera", "--port", "--get-config", "--set-config-value", "--filename"):
        opts[args[i]] = args[i + 1]; i += 2
    else:
        opts[args[i]] = True; i += 1
if "--auto-detect" in opts:
    print("%-30s %-16s" % ("Model", "Port"))
    print("----------------------------------------------------------")
    for model, port in state["cameras"]:
        print("%-30s %-16s" % (model, port))
    sys.exit(0)
widgets = state["widgets"]
if "--list-config" in opts:
    for name in widgets:
        print("/main/capturesettings/" + name)
elif "--get-config" in opts:
    name = opts["--get-config"]
    if name not in widgets:
        error(name + " not found in configuration tree.")
    w = widgets[name]
    print("Label: " + name)
    print("Readonly: 0")
    print("Type: " + ("RADIO" if w["choices"] else "TEXT"))
    print("Current: " + w["current"])
    for k, c in enumerate(w["choices"]):
        print("Choice: %d %s" % (k, c))
    print("END")
elif "--set-config-value" in opts:
    name, value = opts["--set-config-value"].split("=", 1)
    if value not in state.get("ignore", []):
        widgets[name]["current"] = value
    json.dump(state, open(state_path, "w"))
elif "--capture-image-and-download" in opts:
    if state.get("capture_fails"):
        error("An error occurred in the io-library ('I/O problem'): No error description available")
    name = opts["--filename"]
    for suffix in state["suffixes"]:
        with open(name.replace("%C", suffix), "wb") as f:
            f.write(b"RAW" if suffix.lower() != "jpg" else b"JPEG")
    open("tmpfileAbc123", "wb").close()
    print("New file is in location /capt0000.%s on the camera" % state["suffixes"][0])
'''

CANON = {
    "iso": {"current": "100", "choices": ["Auto", "100", "200", "400", "800", "1600", "3200"]},
    "shutterspeed": {"current": "1/60", "choices": ["bulb", "30", "2", "0.3", "1/60", "1/100", "1/125"]},
    "aperture": {"current": "5.6", "choices": ["4", "5.6", "8", "9", "10", "11"]},
    "serialnumber": {"current": "0123456789", "choices": []},
}
NIKON = {
    "iso": {"current": "200", "choices": ["100", "200", "400", "800"]},
    "shutterspeed2": {"current": "1/125", "choices": ["1/250", "1/125", "1/100", "1/60", "Bulb"]},
    "f-number": {"current": "f/8", "choices": ["f/5.6", "f/8", "f/9", "f/10", "f/11"]},
}


@pytest.fixture
def fake(tmp_path, monkeypatch):
    """Install the fake gphoto2; returns a function that (re)writes its state and a log reader."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    program = bin_dir / "gphoto2"
    # -S: no site import, so each call of the fake starts in ~30 ms.
    program.write_text(f"#!{sys.executable} -S\n" + textwrap.dedent(FAKE_GPHOTO2))
    program.chmod(0o755)
    state_path = tmp_path / "state.json"
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("FAKE_GPHOTO2_STATE", str(state_path))

    class Fake:
        def set(self, **state):
            base = {"cameras": [["Canon EOS 5D Mark II", "usb:001,004"]], "widgets": CANON, "suffixes": ["cr2"]}
            state_path.write_text(json.dumps({**base, **state}))

        def calls(self):
            log = Path(str(state_path) + ".log")
            return [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []

        def widgets(self):
            return json.loads(state_path.read_text())["widgets"]

    f = Fake()
    f.set()
    return f


PAPER = ExposureSettings(iso=200, shutter_s=0.01, aperture_f=10.0)


def test_detect_and_identify(fake):
    cam = GPhotoCamera()
    assert isinstance(cam, Camera)
    assert (cam.model, cam.port) == ("Canon EOS 5D Mark II", "usb:001,004")
    assert cam.identify() == "Canon EOS 5D Mark II at usb:001,004, serial 0123456789"
    calls = fake.calls()
    assert calls[0]["args"] == ["--auto-detect"]
    assert all(c["lc_all"] == "C" for c in calls)
    assert all(c["args"][:4] == ["--camera", "Canon EOS 5D Mark II", "--port", "usb:001,004"] for c in calls[1:])


def test_bare_usb_duplicate_is_dropped(fake):
    fake.set(cameras=[["Canon EOS 5D Mark II", "usb:"], ["Canon EOS 5D Mark II", "usb:001,004"]])
    assert detect_cameras() == [("Canon EOS 5D Mark II", "usb:001,004")]


def test_long_model_name_and_choice_by_model(fake):
    long_name = "Nikon DSC D850 (PTP mode) with a very long name"
    fake.set(cameras=[[long_name, "usb:002,007"], ["Canon EOS 5D Mark II", "usb:001,004"]])
    cam = GPhotoCamera(CameraConfig(model="nikon dsc d850 (ptp mode) with a very long name"))
    assert (cam.model, cam.port) == (long_name, "usb:002,007")
    cam = GPhotoCamera(CameraConfig(port="usb:001,004"))
    assert cam.model == "Canon EOS 5D Mark II"


def test_no_camera(fake):
    fake.set(cameras=[])
    with pytest.raises(CameraError, match=r"no camera found by `gphoto2 --auto-detect` \(cameras found: none\)"):
        GPhotoCamera()
    fake.set()
    with pytest.raises(CameraError, match="no camera with model 'Sony A7'.*Canon EOS 5D Mark II at usb:001,004"):
        GPhotoCamera(CameraConfig(model="Sony A7"))


def test_two_cameras_are_ambiguous(fake):
    fake.set(cameras=[["Canon EOS 5D Mark II", "usb:001,004"], ["Canon EOS 5D Mark II", "usb:001,005"]])
    with pytest.raises(CameraError, match="2 cameras match.*set camera.model or camera.port"):
        GPhotoCamera()
    assert GPhotoCamera(CameraConfig(port="usb:001,005")).port == "usb:001,005"


def test_configure_canon_sets_and_reads_back(fake):
    got = GPhotoCamera().configure(PAPER)
    assert got == ExposureSettings(iso=200, shutter_s=0.01, aperture_f=10.0)
    widgets = fake.widgets()
    assert (widgets["iso"]["current"], widgets["shutterspeed"]["current"], widgets["aperture"]["current"]) == (
        "200", "1/100", "10")
    sets = [c["args"][4:] for c in fake.calls() if "--set-config-value" in c["args"]]
    assert sets == [["--set-config-value", "iso=200"], ["--set-config-value", "shutterspeed=1/100"],
                    ["--set-config-value", "aperture=10"]]


def test_configure_nikon_names_and_formats(fake):
    fake.set(cameras=[["Nikon DSC D800E", "usb:002,003"]], widgets=NIKON)
    got = GPhotoCamera().configure(ExposureSettings(iso=800, shutter_s=1 / 60, aperture_f=10))
    assert got == ExposureSettings(iso=800, shutter_s=1 / 60, aperture_f=10.0)
    widgets = fake.widgets()
    assert widgets["shutterspeed2"]["current"] == "1/60" and widgets["f-number"]["current"] == "f/10"


def test_nominal_values_match_within_a_sixth_of_a_stop(fake):
    got = GPhotoCamera().configure(ExposureSettings(iso=400, shutter_s=1 / 3, aperture_f=5.657))
    assert got.shutter_s == pytest.approx(0.3) and got.aperture_f == 5.6
    assert fake.widgets()["shutterspeed"]["current"] == "0.3"


def test_value_the_camera_does_not_offer(fake):
    with pytest.raises(CameraError, match=r"aperture f/22 is not among its values for 'aperture' \(4, 5.6"):
        GPhotoCamera().configure(ExposureSettings(iso=200, shutter_s=0.01, aperture_f=22))


def test_silently_ignored_value_is_caught_by_the_read_back(fake):
    fake.set(ignore=["1/100"])
    with pytest.raises(CameraError) as err:
        GPhotoCamera().configure(PAPER)
    msg = str(err.value)
    assert "shutter asked 1/100 s, the camera reports '1/60'" in msg and "shutterspeed=1/100" in msg


def test_missing_setting_is_named(fake):
    fake.set(widgets={k: v for k, v in CANON.items() if k != "aperture"})
    with pytest.raises(CameraError, match="no aperture setting.*aperture, f-number"):
        GPhotoCamera().configure(PAPER)


def test_capture_downloads_the_raw_file_with_its_suffix(fake, tmp_path):
    dest = tmp_path / "session" / "frames" / "skin_0550"
    written = GPhotoCamera().capture(dest)
    assert written == dest.with_suffix(".cr2")
    assert written.read_bytes() == b"RAW"
    assert sorted(p.name for p in dest.parent.iterdir()) == ["skin_0550.cr2"]  # no temporary left


def test_capture_raw_plus_jpeg_keeps_the_raw(fake, tmp_path):
    fake.set(suffixes=["NEF", "JPG"])
    written = GPhotoCamera().capture(tmp_path / "ref_0450.dng")
    assert written == tmp_path / "ref_0450.NEF"
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_file() and p.suffix != ".json" and p.suffix != ".log") == [
        "ref_0450.NEF"]


def test_capture_jpeg_only_is_refused(fake, tmp_path):
    fake.set(suffixes=["jpg"])
    with pytest.raises(CameraError, match="expected one raw file.*got frame.jpg.*RAW"):
        GPhotoCamera().capture(tmp_path / "dark")
    assert not list(tmp_path.glob("dark*"))


def test_capture_failure_names_the_command_and_stderr(fake, tmp_path):
    fake.set(capture_fails=True)
    with pytest.raises(CameraError) as err:
        GPhotoCamera().capture(tmp_path / "dark")
    msg = str(err.value)
    assert "--capture-image-and-download --filename frame.%C" in msg and "exit 1" in msg
    assert "I/O problem" in msg and "*** Error" not in msg
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".gphoto2-")] == []


def test_time_out_names_the_command(fake):
    fake.set(hang=True)
    with pytest.raises(CameraError, match=r"`gphoto2 --auto-detect` did not finish within 0.5 s"):
        GPhotoCamera(timeout_s=0.5)


def test_missing_program(fake, tmp_path):
    with pytest.raises(CameraError, match="gphoto2 command .* was not found"):
        GPhotoCamera(executable=str(tmp_path / "no-gphoto2"))


@pytest.mark.parametrize(
    ("text", "seconds"),
    [("1/100", 0.01), ("1/8000", 1 / 8000), ("0.3", 0.3), ("2", 2.0), ("30", 30.0), ("1 1/3", 4 / 3),
     ("0.0100s", 0.01), ('2"', 2.0), ("10/1000", 0.01)],
)
def test_parse_shutter(text, seconds):
    assert parse_shutter_s(text) == pytest.approx(seconds)


@pytest.mark.parametrize("text", ["bulb", "Bulb", "Time", "auto", "", "1/0", "0"])
def test_parse_shutter_rejects(text):
    assert parse_shutter_s(text) is None


@pytest.mark.parametrize(("seconds", "text"), [(0.01, "1/100"), (1 / 125, "1/125"), (0.3, "0.3"), (2.0, "2"),
                                               (1.3, "1.3")])
def test_format_shutter_round_trips(seconds, text):
    assert format_shutter_s(seconds) == text
    assert parse_shutter_s(text) == pytest.approx(seconds)


@pytest.mark.parametrize(("text", "f"), [("f/10", 10.0), ("F5.6", 5.6), ("10", 10.0), ("f/2.8", 2.8)])
def test_parse_aperture(text, f):
    assert parse_aperture_f(text) == f
    assert parse_aperture_f("implicit auto") is None
