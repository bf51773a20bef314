"""``skinlayers batch`` on a Dask LocalCluster with tiny simulated sessions (16² cubes, six bands): a
corrupt session is recorded and does not stop the others, a rerun retries only what failed, the study
table equals the one computed session by session, and a worker killed during a task costs nothing."""

from __future__ import annotations

import csv
import math
import os
import shutil
import signal
import threading
import time
from pathlib import Path

import pytest

#: Six bands: one per parameter and the global scale (reconstruct.checks.MIN_BANDS).
BANDS = (430.0, 490.0, 550.0, 580.0, 610.0, 670.0)
SEEDS = (1, 2, 3)


@pytest.fixture(scope="module")
def made_sessions(tmp_path_factory) -> Path:
    """Three simulated sessions of a 16² cube, made once; each test copies them."""
    import yaml

    from skinlayers.acquire.hardware.rig import load_rig
    from skinlayers.demo import simulate_session
    from skinlayers.analyses.truths import demo_scene

    folder = tmp_path_factory.mktemp("made")
    by_nm = {b.wavelength_nm: b for b in load_rig().bands}
    rig = load_rig(bands=[by_nm[b].model_dump() for b in BANDS], geometry={"cube_px": 16, "rectify_px": 128},
                   camera={"driver": "simulated"})
    scene = folder / "scene.yaml"
    scene.write_text(yaml.safe_dump(demo_scene()))
    for seed in SEEDS:
        simulate_session(folder / "study" / f"s{seed}", rig, scene, seed, device="cpu")
    return folder / "study"


@pytest.fixture
def study(made_sessions, tmp_path) -> Path:
    shutil.copytree(made_sessions, tmp_path / "study")
    return tmp_path / "study"


@pytest.fixture(scope="module")
def client():
    """One LocalCluster of two workers for the module (a killed worker is restarted by its nanny)."""
    from distributed import Client

    from skinlayers.studies.batch import local_cluster

    with local_cluster(2) as cluster, Client(cluster) as c:
        yield c


def _light():
    """What the orchestration tests run in each task: calibration and a short fit (the homogeneous model,
    no robust refit, no absorbers) — they test statuses, ledgers and tables, not the maps."""
    from skinlayers.reconstruct import load_fit_settings
    from skinlayers.studies.batch import BatchOptions

    return BatchOptions(fit_settings=load_fit_settings(None, forward="homogeneous", robust_passes=0, absorbers="none"))


def _corrupt(session: Path) -> Path:
    frame = sorted(session.glob("**/*.dng"))[0]
    frame.write_bytes(frame.read_bytes()[:1000])
    return frame


def _leftovers(study: Path) -> list[Path]:
    return [p for p in study.parent.rglob("*") if p.name.startswith((".staging-", ".skinlayers.lock", ".tmp-"))]


def test_a_corrupt_session_fails_alone_and_only_it_is_retried(study, tmp_path, client, run_cli):
    import json

    from skinlayers.studies.batch import read_study, reconstruction_dir, run_batch
    from skinlayers.studies.study import session_summary

    bad = _corrupt(study / "s2")
    sessions = read_study(study)
    out = tmp_path / "out"
    first = run_batch(sessions, _light(), out, client=client)
    assert {n: o.status for n, o in first.outcomes.items()} == {"s1": "done", "s2": "failed", "s3": "done"}
    assert bad.name in first.outcomes["s2"].error and "\n" not in first.outcomes["s2"].error
    assert not (study / "s2_calibrated" / "calibration.json").exists()
    assert not (study / "s2_reconstruction").exists()
    fits = [reconstruction_dir(s.path) / "fit.json" for s in (sessions[0], sessions[2])]
    stamps = [f.stat().st_mtime_ns for f in fits]

    code, stdout, err = run_cli("batch", str(study), "-o", str(out), "--workers", "2")  # the command, its own LocalCluster
    assert code == 1 and "failed: s2: " in stdout and "1 failed" in stdout, stdout + err
    ledger = json.loads((out / "batch.json").read_text())["sessions"]
    assert [(ledger[n]["status"], ledger[n]["ran"]) for n in ("s1", "s2", "s3")] == [("skipped", []), ("failed", []), ("skipped", [])]
    assert stamps == [f.stat().st_mtime_ns for f in fits]
    assert _leftovers(study) == []

    rows = {r["session"]: r for r in csv.DictReader((out / "study.csv").open())}
    for s in (sessions[0], sessions[2]):  # the table equals the one computed session by session
        expected = session_summary(reconstruction_dir(s.path))
        assert {k: float(rows[s.name][k]) for k in expected} == pytest.approx(expected, rel=0, abs=0, nan_ok=True)
        assert rows[s.name]["subject"] == "demo" and rows[s.name]["status"] == "skipped"
    assert rows["s2"]["status"] == "failed" and rows["s2"]["C_m_trimmed_mean"] == ""
    assert (out / "study_maps.png").stat().st_size > 0 and json.loads((out / "study.json").read_text())["reconstructed"] == 2


def test_a_worker_killed_during_a_task_costs_no_session(study, tmp_path, client):
    from skinlayers.studies.batch import read_study, reconstruction_dir, run_batch

    sessions = read_study(study)
    assert set(client.run(lambda: os.environ.get("MALLOC_TRIM_THRESHOLD_")).values()) == {None}  # batch.WORKER_ENVIRON
    result: dict = {}
    runner = threading.Thread(target=lambda: result.update(r=run_batch(sessions, _light(), tmp_path / "out", client=client)))
    runner.start()
    busy = _busy_worker(client)
    killed_task = next(iter(client.processing()[busy]))
    time.sleep(1.0)  # well inside the task: the calibration or the fit is writing its staging folder
    pid = client.run(os.getpid, workers=[busy])[busy]
    os.kill(pid, signal.SIGKILL)
    runner.join(timeout=300)
    assert not runner.is_alive()
    outcomes = result["r"].outcomes
    assert sorted(outcomes) == ["s1", "s2", "s3"] and all(o.status == "done" for o in outcomes.values()), outcomes
    for s in sessions:
        assert (reconstruction_dir(s.path) / "fit.json").is_file()
    assert _leftovers(study) == []
    processing = [entry for entry in client.story(killed_task) if entry[0] == "scheduler" and entry[2] == "processing"]
    assert len(processing) == 2  # the task was running when its worker died, and ran again


def _busy_worker(client, timeout_s: float = 60.0) -> str:
    """The address of a worker running a task (waits for one)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        busy = [w for w, tasks in client.processing().items() if tasks]
        if busy:
            return busy[0]
        time.sleep(0.05)
    raise AssertionError("no task started")


def test_the_study_statistics_on_a_constructed_table():
    from skinlayers.studies.study import group_statistics, principal_components, trimmed_mean, visit_changes

    assert trimmed_mean([*range(1, 10), 1000.0]) == pytest.approx(5.5)  # the largest and the smallest of ten cut
    rows = [{"session": f"v{i}", "subject": "a" if i < 2 else "b", "site": "arm", "date": f"2026-0{i + 1}-01",
             **{f"{m}_trimmed_mean": float(i + 1) * (2.0 if m == "C_hd" else 1.0) for m in ("C_m", "beta_m", "C_he", "C_bc", "C_hd")}}
            for i in range(4)]
    groups = group_statistics(rows, "subject")
    assert groups["a"]["sessions"] == 2 and groups["a"]["C_m"]["trimmed_mean"] == pytest.approx(1.5)
    assert groups["b"]["C_hd"]["sd"] == pytest.approx(math.sqrt(2.0))
    pca = principal_components(rows)  # every map a multiple of the session's index: one component holds it all
    assert pca["explained"][0] == pytest.approx(1.0)
    changes = visit_changes(rows)
    assert [(c["from"], c["to"]) for c in changes] == [("v0", "v1"), ("v2", "v3")]
    assert changes[0]["change"]["C_hd"] == pytest.approx(2.0) and changes[1]["relative_change"]["C_m"] == pytest.approx(1 / 3)


@pytest.mark.parametrize("text, words", [
    ("subject,site\nA,arm\n", "'session' column"),
    ("session,subject\ns1,A\ns1,B\n", "listed twice"),
    ("session,subject\n,A\n", "line 2: no session"),
])
def test_a_bad_study_list_is_refused_in_one_line(tmp_path, run_cli, text, words):
    listing = tmp_path / "study.csv"
    listing.write_text(text)
    code, _, err = run_cli("batch", str(listing))
    assert code == 1 and words in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_bad_options_are_refused_before_any_worker_starts(study, run_cli):
    code, _, err = run_cli("batch", str(study), "--steps", "calibrate,paint")
    assert code == 1 and "--steps" in err
    code, _, err = run_cli("batch", str(study / "s1" / "truth"))
    assert code == 1 and "no sessions" in err
    code, _, err = run_cli("batch", str(study), "--workers", "2", "--scheduler", "tcp://127.0.0.1:1")
    assert code == 1 and "--workers" in err


def test_a_csv_study_keeps_its_columns_and_groups_by_them(tmp_path):
    import json

    from skinlayers.studies.batch import SessionOutcome, read_study, write_study

    (tmp_path / "listing.csv").write_text("session,subject,skin_type\nA/v1,A,II\nA/v2,A,II\nB/v1,,V\n")
    sessions = read_study(tmp_path / "listing.csv")
    assert [s.path for s in sessions] == [tmp_path / "A/v1", tmp_path / "A/v2", tmp_path / "B/v1"]
    summary = lambda k: {"pixels": 1, **{f"{m}_trimmed_mean": float(k) for m in ("C_m", "beta_m", "C_he", "C_bc", "C_hd")}}  # noqa: E731
    outcomes = {"A/v1": SessionOutcome("A/v1", "done", manifest={"subject": "ignored", "site": "arm"}, summary=summary(1)),
                "A/v2": SessionOutcome("A/v2", "done", manifest={"site": "arm"}, summary=summary(3)),
                "B/v1": SessionOutcome("B/v1", "failed", error="InputError: a frame is damaged")}
    write_study(tmp_path / "out", sessions, outcomes, figures=False)
    rows = list(csv.DictReader((tmp_path / "out" / "study.csv").open()))
    assert [(r["subject"], r["site"], r["skin_type"], r["status"]) for r in rows] == [
        ("A", "arm", "II", "done"), ("A", "arm", "II", "done"), ("", "", "V", "failed")]  # the list's columns win
    record = json.loads((tmp_path / "out" / "study.json").read_text())
    assert record["reconstructed"] == 2 and record["failed"] == {"B/v1": "InputError: a frame is damaged"}
    assert record["groups"] == {}  # both reconstructed sessions share every column: nothing to group
    record = write_study(tmp_path / "out2", sessions, outcomes, group_by=["skin_type"], figures=False)
    groups = json.loads((tmp_path / "out2" / "study.json").read_text())["groups"]["skin_type"]
    assert groups["II"]["sessions"] == 2 and groups["II"]["C_m"]["trimmed_mean"] == pytest.approx(2.0)


def test_a_step_cut_short_before_its_marker_is_run_again(study):
    from skinlayers.studies.batch import BatchOptions, process_session, read_study

    stale = study / "s1_calibrated" / "cube.exr"  # moved into place; the marker never written
    stale.parent.mkdir()
    stale.write_bytes(b"half of an earlier attempt")
    outcome = process_session(read_study(study)[0], BatchOptions())
    assert (outcome.status, outcome.ran) == ("done", ("calibrate", "reconstruct")), outcome.error
    assert stale.read_bytes()[:4] == b"\x76\x2f\x31\x01"  # an OpenEXR file now


def test_the_statistics_survive_what_a_study_holds():
    """A calibration alone (no maps), a session without subject or site, a session with a map not finite."""
    import json

    from skinlayers.studies.study import correlations, study_record, visit_changes

    maps = ("C_m", "beta_m", "C_he", "C_bc", "C_hd")
    stats = lambda k: {"pixels": 10, **{f"{m}_trimmed_mean": float(k + j) * (k + 1) for j, m in enumerate(maps)}}  # noqa: E731
    rows = [{"session": f"s{k}", "subject": "", "site": "", "date": f"2026-01-0{k + 1}", "status": "done", **stats(k)} for k in range(4)]
    rows[3]["C_he_trimmed_mean"] = math.nan
    calibrated_only = {"session": "c", "subject": "", "site": "", "date": "", "status": "done"}
    record = study_record([*rows, calibrated_only])
    assert record["reconstructed"] == 4 and visit_changes(rows) == []  # nobody's visits are chained
    assert correlations(rows)["maps"] == list(maps) and len(correlations(rows)["matrix"]) == 5  # s3 left out, not C_he
    json.dumps(record)  # no NaN object left unwritable


@pytest.mark.parametrize("header, words", [("session,site,site", "site"), ("session,status", "status"),
                                           ("session,C_m_median", "C_m_median")])
def test_a_study_list_may_not_repeat_or_take_the_tables_columns(tmp_path, header, words):
    from skinlayers.studies.batch import read_study
    from skinlayers.formats.errors import InputError

    listing = tmp_path / "study.csv"
    listing.write_text(header + "\n" + ",".join(["s1"] + ["x"] * (header.count(","))) + "\n")
    with pytest.raises(InputError, match=words):
        read_study(listing)


def test_an_unknown_group_is_refused_before_any_work(study, run_cli):
    code, _, err = run_cli("batch", str(study), "--group", "skin_type")
    assert code == 1 and "--group skin_type" in err and "subject" in err


_FAULTS_PROBE = """
import resource, sys
import torch
if sys.argv[1] == "1":
    from skinlayers.studies.allocator import use_task_allocator
    assert use_task_allocator()
x = torch.ones(1 << 20)
for _ in range(20):
    x = x * 1.0001  # warm: every product is a fresh 4-MiB tensor, the one before freed
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(100):
    x = x * 1.0001
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="glibc's malloc on Linux")
def test_a_task_undoes_the_nannys_malloc_setting(tmp_path):
    """Under Dask's ``MALLOC_TRIM_THRESHOLD_=65536`` every 4-MiB tensor is mapped anew (a page fault per
    page); after ``use_task_allocator`` the heap serves them again, as in a plain process."""
    import subprocess
    import sys

    from skinlayers.studies.allocator import use_task_allocator

    assert not use_task_allocator({})  # a plain environment: nothing to undo
    probe = tmp_path / "probe.py"
    probe.write_text(_FAULTS_PROBE)
    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536"}
    faults = {fix: int(subprocess.run([sys.executable, str(probe), fix], env=env, capture_output=True, text=True,
                                      check=True).stdout) for fix in ("0", "1")}
    pages = 100 * (4 << 20) // 4096
    assert faults["0"] > pages // 2, faults  # the setting's cost, as the nanny leaves it
    assert faults["1"] < pages // 20, faults


def test_cubes_from_other_cameras_are_fitted_beside_the_sessions(study, tmp_path, client):
    """Issue 59: a study folder holding ENVI cubes beside its sessions fits them (no calibration), each
    into ``<STEM>_reconstruction``, to the maps of the same cube fitted from its session; a CSV gives a
    ``.npz`` that does not say its pixel side its ``mm_per_pixel``, and without it the cube fails alone."""
    import numpy as np

    from skinlayers.calibration import calibrate_session
    from skinlayers.formats.cube import read_cube
    from skinlayers.formats.foreign.cubes import write_cube_file
    from skinlayers.model.patch.maps_io import read_maps
    from skinlayers.studies.batch import fit_dir, read_study, reconstruction_dir, run_batch

    for seed in SEEDS[1:]:
        shutil.rmtree(study / f"s{seed}")
    calibrate_session(study / "s1", study / "s1_calibrated")
    cube = read_cube(study / "s1_calibrated" / "cube.exr")
    (study / "camera").mkdir()
    write_cube_file(study / "camera" / "arm.hdr", cube)
    assert [s.name for s in read_study(study)] == ["camera/arm.hdr", "s1"]  # not the calibrated cube.exr

    result = run_batch(read_study(study), _light(), tmp_path / "out", client=client)
    assert {n: o.ran for n, o in result.outcomes.items()} == {"camera/arm.hdr": ("reconstruct",), "s1": ("reconstruct",)}
    assert fit_dir(study / "camera" / "arm.hdr") == study / "camera" / "arm_reconstruction"
    ours, theirs = read_maps(reconstruction_dir(study / "s1") / "maps.exr"), read_maps(study / "camera" / "arm_reconstruction" / "maps.exr")
    assert all(np.array_equal(getattr(ours, n).numpy(), getattr(theirs, n).numpy()) for n in ("C_m", "beta_m", "C_he", "C_hd"))

    write_cube_file(tmp_path / "full.npz", cube)
    with np.load(tmp_path / "full.npz") as f:
        np.savez(tmp_path / "bare.npz", **{k: f[k] for k in f.files if k != "mm_per_pixel"})
    shutil.copy(tmp_path / "bare.npz", tmp_path / "bare2.npz")
    listing = tmp_path / "study.csv"
    listing.write_text(f"session,mm_per_pixel\nbare.npz,{cube.header.mm_per_pixel!r}\nbare2.npz,\n")
    outcomes = run_batch(read_study(listing), _light(), tmp_path / "out2", client=client).outcomes
    assert outcomes["bare.npz"].status == "done" and (tmp_path / "bare_reconstruction" / "fit.json").is_file()
    assert outcomes["bare2.npz"].status == "failed" and "mm" in outcomes["bare2.npz"].error and "\n" not in outcomes["bare2.npz"].error


def test_what_a_study_folder_takes_for_a_cube_and_where_each_fit_goes(tmp_path):
    from skinlayers.formats.errors import InputError
    from skinlayers.studies.batch import fit_dir, read_study, reconstruction_dir

    study = tmp_path / "study"
    (study / "2024.05.01").mkdir(parents=True)
    (study / "2024.05.01" / "manifest.json").write_text("{}")
    (study / "2024.05.01" / "frame.tif").write_bytes(b"")  # inside a session: its own, not a cube
    (study / "cam").mkdir()
    for name in ("arm.hdr", "DARKREF_arm.hdr", "WHITEREF_arm.hdr"):
        (study / "cam" / name).write_bytes(b"")
    (study / "cam_reconstruction").mkdir()
    (study / "cam_reconstruction" / "old.npz").write_bytes(b"")  # the commands' outputs are not cubes
    assert [s.name for s in read_study(study)] == ["2024.05.01", "cam/arm.hdr"]
    assert fit_dir(study / "2024.05.01") == reconstruction_dir(study / "2024.05.01")  # a dotted session folder
    assert read_study(study / "2024.05.01")[0].name == "2024.05.01"  # a session as the study: its frames are not cubes
    (study / "cam" / "arm.tif").write_bytes(b"")
    with pytest.raises(InputError, match="both be fitted into"):
        read_study(study)
