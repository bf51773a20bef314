"""Benchmarks of the heterogeneous renderer (on demand: ``pytest -m bench tests/bench/test_bench_renderer.py -s``).

Each configuration runs in a fresh process (``render_run.py``) so that peak memory is its own.
Writes to ``bench_results/`` (or ``$SKINLAYERS_BENCH_DIR``):

- ``render_speed.csv``: forward and forward + backward time and peak memory of the paper's case — a
  256×256 patch (7.5 mm) with its 1 cm border at 9 bands — per blur strategy, on the CPU here and on
  CUDA when one is present;
- ``render_tradeoffs.csv`` / ``render_tradeoffs.png``: time against error for the number of Gaussians,
  the inter-scattering terms and the grid size, against a high-fidelity reference render.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
import torch

from bench_io import out_dir, write_csv

pytestmark = pytest.mark.bench

HERE = Path(__file__).resolve().parent
PAPER = {"size": 256, "mm": 7.5 / 256, "bands": 9, "border_mm": 10.0}



def run(cfg: dict, timeout: int = 3000) -> dict:
    proc = subprocess.run([sys.executable, str(HERE / "render_run.py"), json.dumps(cfg)], capture_output=True,
                          text=True, timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr[-2000:])
    return json.loads(proc.stdout.strip().splitlines()[-1])



#: The renderer as it stood before the speed work: no weight cache, no series closure, tolerance 1e-3.
PLAIN = {"series_closure": False, "weight_cache_mb": 0, "series_tolerance": 1e-3}


#: The forward models side by side (issue 15): DWRR08's, transport profiles with its rule, the default.
FORWARD_MODELS = {
    "paper (diffusion, exit rule)": {"profiles": "diffusion", "render": {"coupling": "exit"}},
    "transport profiles, exit rule": {"profiles": "transport", "render": {"coupling": "exit"}},
    "transport profiles, exit rule, Lambertian hand-over": {"profiles": "transport", "handover": "lambertian",
                                                            "render": {"coupling": "exit"}},
    "transport profiles, segment coupling": {"profiles": "transport", "render": {"coupling": "segment"}},
}


def test_forward_models_speed_and_memory():
    """Forward and forward + backward time and peak memory of the three forward models, each run in a
    fresh process, interleaved, three rounds at 128² and one at the paper's case (256², 10-mm border);
    the medians and the ratios to DWRR08's model in one run (``forward_models.csv``)."""
    cases = {"128 px, 0.05 mm, 5-mm border": {"size": 128, "mm": 0.05, "bands": 9, "border_mm": 5.0},
             "paper case, 256 px, 10-mm border": PAPER}
    only = os.environ.get("SKINLAYERS_FORWARD_CASES")  # e.g. "128" for the small case alone
    if only:
        cases = {k: v for k, v in cases.items() if str(v["size"]) in only.split(",")}
    rows = []
    for case, base in cases.items():
        rounds = 3 if base["size"] <= 128 else 1
        got = {name: [] for name in FORWARD_MODELS}
        for _ in range(rounds):
            for name, over in FORWARD_MODELS.items():
                got[name].append(run({**base, "backward": True, **over}))
        paper = FORWARD_MODELS and got["paper (diffusion, exit rule)"]
        med = lambda runs, key: statistics.median(r[key] for r in runs)  # noqa: E731
        for name, runs in got.items():
            fw, bw = med(runs, "forward_s"), med(runs, "backward_s")
            p_fw, p_bw = med(paper, "forward_s"), med(paper, "backward_s")
            rows.append({"case": case, "model": name, "rounds": rounds, "forward_s": round(fw, 2),
                         "forward_backward_s": round(fw + bw, 2), "forward_vs_paper": round(fw / p_fw, 2),
                         "forward_backward_vs_paper": round((fw + bw) / (p_fw + p_bw), 2),
                         "peak_rss_mb": round(max(r["peak_rss_mb"] for r in runs)), "terms": runs[0]["terms"],
                         "handover_grid_s": round(med(runs, "handover_grid_s"), 2) if "handover_grid_s" in runs[0] else ""})
    write_csv("forward_models.csv", rows, "medians; ratios against DWRR08's model measured in the same run")
    assert all(r["forward_s"] > 0 for r in rows)


def test_paper_case_speed_and_memory():
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    rows = []

    def row(r, device, blur, backward, label):
        rows.append({"device": device, "blur": blur, "pass": ("forward+backward" if backward else "forward") + label,
                     "grid": "x".join(map(str, r["grid"])), "terms": r["terms"],
                     "forward_s": round(r["forward_s"], 2), "backward_s": round(r.get("backward_s", 0.0), 2),
                     "peak_rss_mb": round(r["peak_rss_mb"]), "peak_device_mb": round(r.get("peak_device_mb", 0))})

    for device in devices:
        for blur in ("pyramid", "fft"):
            for backward in (False, True):
                if blur == "fft" and backward and device == "cpu":
                    continue  # minutes per run on two cores; the forward shows the ratio
                row(run({**PAPER, "blur": blur, "backward": backward, "device": device}), device, blur, backward, "")
        # side by side: the same case without the weight cache and the closure; and the default 5 mm border
        row(run({**PAPER, "blur": "pyramid", "device": device, "render": PLAIN}), device, "pyramid", False, " (plain series)")
        for backward in (False, True):
            row(run({**PAPER, "border_mm": 5.0, "blur": "pyramid", "backward": backward, "device": device}),
                device, "pyramid", backward, " (5 mm border)")
    # the chain is exact but slow: timed on a quarter of the area, same physical size
    small = {**PAPER, "size": 128, "mm": 7.5 / 128}
    for blur in ("chain", "pyramid", "fft"):
        r = run({**small, "blur": blur})
        rows.append({"device": "cpu", "blur": blur, "pass": "forward (128² patch)", "grid": "x".join(map(str, r["grid"])),
                     "terms": r["terms"], "forward_s": round(r["forward_s"], 2), "backward_s": 0.0,
                     "peak_rss_mb": round(r["peak_rss_mb"]), "peak_device_mb": 0})
    write_csv("render_speed.csv", rows)
    for r in rows:
        if r["pass"] == "forward+backward":
            assert r["peak_rss_mb"] < 4096 or r["peak_device_mb"] < 4096


def test_time_against_error():
    """Error (relative RMS over the window, against a reference: 21 Gaussians, FFT blurs, 12 terms,
    the same grid) and time, varying one knob at a time around the defaults."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    base = {"size": 96, "mm": 0.06, "bands": 5, "border_mm": 8.0}
    tmp = Path(tempfile.mkdtemp())

    def render(name: str, **cfg) -> tuple[dict, torch.Tensor]:
        path = tmp / f"{name}.pt"
        r = run({**base, **cfg, "save": str(path)})
        return r, torch.load(path)

    _, ref = render("ref", blur="fft", terms=12, render={"series_closure": False})
    rows = []

    def error(img: torch.Tensor, ref_img: torch.Tensor) -> float:
        return float(torch.sqrt(((img - ref_img) ** 2).mean()) / torch.sqrt((ref_img**2).mean()))

    for k, std in ((21, 0.01 / 2**1.5), (18, 0.01), (15, 0.01 * 2**1.5), (12, 0.08)):
        r, img = render(f"k{k}", tables={"n_gaussians": k, "gaussian_std_min_mm": std})
        rows.append({"knob": "gaussians", "value": k, "seconds": round(r["forward_s"], 3), "rel_rms_error": error(img, ref)})
    for terms in (1, 2, 3, 4, 6, 8, 10):
        r, img = render(f"t{terms}", terms=terms, render={"series_closure": False})
        rows.append({"knob": "terms", "value": terms, "seconds": round(r["forward_s"], 3), "rel_rms_error": error(img, ref)})
        r, img = render(f"c{terms}", terms=terms)
        rows.append({"knob": "terms (closed)", "value": terms, "seconds": round(r["forward_s"], 3),
                     "rel_rms_error": error(img, ref)})
    for border in (1.0, 2.0, 3.0, 5.0):
        r, img = render(f"b{border}", border_mm=border)
        rows.append({"knob": "border (mm)", "value": border, "seconds": round(r["forward_s"], 3), "rel_rms_error": error(img, ref)})
    for scale in (1, 2, 4):
        cfg = {"size": base["size"] // scale, "mm": base["mm"] * scale}
        r, img = render(f"g{scale}", **cfg)
        # compare with the full-resolution reference averaged down to this grid
        down = torch.nn.functional.avg_pool2d(ref[0], scale)[None] if scale > 1 else ref
        rows.append({"knob": "grid (mm/px)", "value": round(base["mm"] * scale, 3), "seconds": round(r["forward_s"], 3),
                     "rel_rms_error": error(img, down)})
    for mp in (2.0, 3.0, 5.0):
        r, img = render(f"p{mp}", render={"pyramid_min_px": mp})
        rows.append({"knob": "pyramid_min_px", "value": mp, "seconds": round(r["forward_s"], 3), "rel_rms_error": error(img, ref)})
    write_csv("render_tradeoffs.csv", rows)
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for knob in dict.fromkeys(r["knob"] for r in rows):
        pts = [r for r in rows if r["knob"] == knob]
        ax.plot([p["seconds"] for p in pts], [max(p["rel_rms_error"], 1e-6) for p in pts], "o-", label=knob)
        for p in pts:
            ax.annotate(str(p["value"]), (p["seconds"], max(p["rel_rms_error"], 1e-6)), fontsize=7,
                        textcoords="offset points", xytext=(3, 3))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("forward time (s, CPU)")
    ax.set_ylabel("relative RMS error vs reference")
    ax.set_title("Renderer: time against error (window light, 5 bands)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir() / "render_tradeoffs.png", dpi=120)
    plt.close(fig)
