"""The capture session on the simulated rig: the protocol, the manifest, faults, interruption, resume,
never overwriting, and the `capture` command (simulated, and a virtual wheel on a real pty)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from skinlayers.acquire.hardware.devices import CameraError, WheelError
from skinlayers.formats.manifest import ManifestError, read_manifest
from skinlayers.formats.files import file_sha256
from skinlayers.acquire.hardware.rig import load_rig
from skinlayers.acquire.session import AutoOperator, SessionError, plan_session, run_session
from skinlayers.acquire.hardware.simdevices import SimulatedCamera, SimulatedWheel
from skinlayers.acquire.simulator.simulated import SimulatedBench
from skinlayers.acquire.simulator.simulation_settings import simulation_from_dict

BANDS = [{"wavelength_nm": 460, "filter_position": 3, "iso": 200}, {"wavelength_nm": 580, "filter_position": 7, "iso": 400}]
GEOMETRY = {"cube_px": 32, "rectify_px": 160}
SIM = {"filters": {"wavelength_samples": 1}}


def small_rig():
    return load_rig(bands=BANDS, geometry=GEOMETRY, camera={"driver": "simulated"})


def devices(seed: int = 3, **faults):
    bench = SimulatedBench(small_rig(), None, simulation_from_dict(SIM), seed=seed, device="cpu")
    wheel = SimulatedWheel(12, time_scale=0.0, **{k: v for k, v in faults.items() if k != "fail_captures"})
    camera = SimulatedCamera(bench, wheel, fail_captures=faults.get("fail_captures", ()))
    return bench, wheel, camera


def capture(folder: Path, seed: int = 3, resume: bool = False, operator=None, **faults):
    bench, wheel, camera = devices(seed, **faults)
    operator = operator or AutoOperator(bench.set_target)
    return run_session(folder, bench.rig_as_used(), wheel, camera, operator, resume=resume, simulated=True)


def hashes(folder: Path) -> dict[str, str]:
    return {p.name: file_sha256(p) for p in sorted(folder.iterdir()) if p.is_file()}


def test_protocol_order_and_exposures():
    plan = plan_session(small_rig())
    assert [(p.role, p.band_nm) for p in plan] == [("dark", None), ("reference", 460), ("reference", 580),
                                                   ("skin", 460), ("skin", 580)]
    assert plan[0].filter_position == 1 and plan[0].exposure.iso == 400  # the noisiest exposure of the rig
    assert [p.exposure.iso for p in plan[1:]] == [200, 400, 200, 400]


def test_a_session_records_every_frame(tmp_path):
    folder = tmp_path / "s"
    summary = capture(folder)
    m = read_manifest(folder)
    assert summary.complete and m.status == "complete" and summary.frames_taken == 5
    assert [f.file for f in m.frames] == ["dark.dng", "reference_460nm.dng", "reference_580nm.dng",
                                          "skin_460nm.dng", "skin_580nm.dng"]
    for f in m.frames:
        assert file_sha256(folder / f.file) == f.sha256
    assert m.rig_config().geometry.gray_card_roi_px is not None  # the bench's card region travels with the session
    assert not list(folder.glob(".*"))  # no temporary files left
    with pytest.raises(SessionError, match="never overwritten"):
        capture(folder)


def test_a_camera_fault_leaves_a_resumable_session_that_ends_as_an_unbroken_one(tmp_path):
    broken, whole = tmp_path / "broken", tmp_path / "whole"
    with pytest.raises(CameraError):
        capture(broken, fail_captures={4})
    m = read_manifest(broken)
    assert m.status == "in_progress" and len(m.frames) == 3
    before = hashes(broken)
    assert not list(broken.glob(".partial-*"))
    summary = capture(broken, resume=True)
    assert summary.frames_before == 3 and summary.frames_taken == 2
    after = hashes(broken)
    assert all(after[name] == h for name, h in before.items() if name.endswith(".dng"))  # nothing taken twice
    capture(whole)
    assert {k: v for k, v in hashes(whole).items() if k.endswith(".dng")} == {
        k: v for k, v in after.items() if k.endswith(".dng")}


def test_interrupted_at_a_prompt_then_resumed(tmp_path):
    class Impatient(AutoOperator):
        def place(self, target, instruction):
            if target == "skin":
                raise KeyboardInterrupt
            super().place(target, instruction)

    folder = tmp_path / "s"
    bench, wheel, camera = devices()
    with pytest.raises(KeyboardInterrupt):
        run_session(folder, bench.rig_as_used(), wheel, camera, Impatient(bench.set_target))
    assert read_manifest(folder).status == "in_progress" and len(read_manifest(folder).frames) == 3
    operator = AutoOperator()
    bench, wheel, camera = devices()
    operator.on_place = bench.set_target
    run_session(folder, bench.rig_as_used(), wheel, camera, operator, resume=True)
    assert operator.placed == ["skin"]  # the operator is asked again only for what is left
    assert read_manifest(folder).status == "complete"


def test_wrong_wheel_position_stops_the_session_cleanly(tmp_path):
    folder = tmp_path / "s"
    with pytest.raises(WheelError):
        capture(folder, wrong_position={2: 5})
    assert len(read_manifest(folder).frames) == 1


def test_resume_refuses_a_changed_frame_a_bad_name_and_another_rig(tmp_path):
    folder = tmp_path / "s"
    with pytest.raises(CameraError):
        capture(folder, fail_captures={3})
    dark = folder / "dark.dng"
    data = dark.read_bytes()
    dark.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
    with pytest.raises(SessionError, match="changed since it was captured"):
        capture(folder, resume=True)
    dark.write_bytes(data)
    bench, wheel, camera = devices()
    other = bench.rig_as_used().model_copy(update={"name": "another rig"})
    with pytest.raises(SessionError, match="another rig"):
        run_session(folder, other, wheel, camera, AutoOperator(bench.set_target), resume=True)
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["frames"][0]["file"] = "../../etc/passwd"
    (folder / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ManifestError, match="would leave the session folder"):
        read_manifest(folder)
    with pytest.raises(SessionError, match="would leave the session folder"):
        capture(folder, resume=True)




@pytest.fixture
def rig_file(tmp_path):
    import yaml

    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"name": "small", "bands": BANDS, "geometry": GEOMETRY}))
    sim = tmp_path / "sim.yaml"
    sim.write_text(yaml.safe_dump(SIM))
    return path, sim


def test_capture_command_simulated(tmp_path, rig_file, run_cli):
    rig, sim = rig_file
    out = tmp_path / "session"
    args = ["capture", "--sim", "--rig", str(rig), "--sim-settings", str(sim), "--out", str(out), "--yes",
            "--sim-wheel-time", "0", "--device", "cpu"]
    code, stdout, err = run_cli(*args)
    assert code == 0, err
    assert "5 taken now" in stdout and "skinlayers calibrate" in stdout
    assert (out / "truth" / "reflectance.exr").exists() and read_manifest(out).simulated
    code, _, err = run_cli(*args)
    assert code == 1 and err.startswith("error:") and "never overwritten" in err and "Traceback" not in err
    code, stdout, _ = run_cli(*args, "--resume")
    assert code == 0 and "0 taken now, 5 before" in stdout


def test_capture_command_with_a_virtual_wheel_on_a_pty(tmp_path, rig_file, run_cli):
    from skinlayers.acquire.hardware.virtual_fw102c import VirtualFW102C

    rig, sim = rig_file
    out = tmp_path / "bench"
    with VirtualFW102C(12, half_turn_s=0.01) as wheel:
        code, stdout, err = run_cli("capture", "--sim-camera", "--wheel-port", wheel.port,
                                    "--rig", str(rig), "--sim-settings", str(sim), "--out", str(out), "--yes",
                                    "--device", "cpu")
        assert code == 0, err
        assert "FW102C" in err or "fw102c" in err.lower()
        assert [c for c in wheel.received if c.startswith("pos=")] == ["pos=1", "pos=3", "pos=7", "pos=3", "pos=7"]
    assert read_manifest(out).status == "complete"


def test_capture_command_refuses_what_it_cannot_do(tmp_path, run_cli):
    code, _, err = run_cli("capture", "--sim-camera", "--out", str(tmp_path / "x"))
    assert code == 1 and "--wheel-port" in err
    code, _, err = run_cli("capture", "--sim-camera", "--wheel-port", "/dev/nonexistent-port",
                           "--out", str(tmp_path / "y"), "--yes")
    assert code == 1 and "/dev/nonexistent-port" in err and "Traceback" not in err
    assert not (tmp_path / "y").exists()


def test_each_frame_is_logged_for_skinlayers_v(tmp_path, caplog):
    """``skinlayers -v``: one line per frame taken, its role, band, filter and file."""
    with caplog.at_level(logging.INFO, logger="skinlayers.acquire.session"):
        capture(tmp_path / "s")
    said = [r.getMessage() for r in caplog.records if r.name == "skinlayers.acquire.session"]
    assert len(said) == 5, said
    assert said[0].startswith("dark frame: filter 1") and said[0].endswith("dark.dng")
    assert said[-1].startswith("skin frame 580 nm: filter 7") and said[-1].endswith("skin_580nm.dng")
