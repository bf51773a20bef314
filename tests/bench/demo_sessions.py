"""Simulated demo sessions for the benchmarks, made once and kept in ``bench_io.out_dir()``.

``calibrated_session(name, seed, scene)`` runs ``skinlayers demo`` (the simulated rig: a 512² scene
through the optics, camera noise and the calibration into a 256² cube) into ``out_dir()/name`` unless
the session and its cube are already there, and returns the folder (``session/`` with ``truth/``,
``calibrated/cube.exr``). ``refit(folder, settings, name)`` fits the cube again into ``folder/name``
and returns the fit and the accuracy against the truth (``skinlayers.demo.accuracy_against_truth``).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from bench_io import out_dir

__all__ = ["calibrated_session", "refit"]


def calibrated_session(name: str, seed: int, scene: str | None = None) -> Path:
    folder = out_dir() / name
    if not (folder / "calibrated" / "cube.exr").exists() or not (folder / "session" / "truth").exists():
        cmd = [sys.executable, "-m", "skinlayers", "demo", "--seed", str(seed), "-o", str(folder)]
        subprocess.run(cmd + (["--scene", scene] if scene else []), check=True)
    return folder


def refit(folder: Path, settings, name: str = "reconstruction"):
    import torch

    from skinlayers.demo import accuracy_against_truth
    from skinlayers.reconstruct.results.outputs import reconstruct_cube

    torch.set_num_threads(2)
    fit, _ = reconstruct_cube(folder / "calibrated" / "cube.exr", folder / name, settings, device="cpu", force=True)
    return fit, accuracy_against_truth(folder / "session", folder / name, folder / "calibrated" / "cube.exr")
