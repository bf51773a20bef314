"""A study's statistics over its sessions' maps: DWRR08 §7 and Table 2 per group, and more.

Each session that was reconstructed gives one row (``session_summary``): per map its trimmed mean,
median, spread and 10th/90th percentiles over the *scored* pixels (``demo.scored_pixels``: visible, not
flagged for a high residual or a hair, as every accuracy figure of the project counts them). Across
the sessions of a study (``study_record``):

- per group of any column of the study (skin type, site, subject, …): the sessions' count, the trimmed
  mean of their trimmed means and the sessions' standard deviation, per map (Table 2 reports the mean
  parameters of its groups);
- the correlation of the maps across sessions (Pearson, of the sessions' trimmed means);
- a principal component analysis of the sessions' standardised trimmed means (which maps vary
  together across the cohort, and how much of the spread each component holds);
- the change between consecutive visits of the same subject and site (ordered by date).

Means are trimmed (``TRIM`` from each end) because a session's pixels hold freckles, scars and the odd
failed pixel, and a cohort the odd failed session: a plain mean follows them, a median throws away
most of the data.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from ..formats.files import atomic_write

__all__ = ["MAPS", "STATS", "TRIM", "correlations", "grouping_columns", "group_statistics", "principal_components",
           "is_map_column", "reconstructed", "session_summary", "study_record", "trimmed_mean", "visit_changes", "without_nan", "write_study_json",
           "write_study_table"]

MAPS = ("C_m", "beta_m", "C_he", "C_bc", "C_hd")
#: What each session's row holds per map (over its scored pixels).
STATS = ("trimmed_mean", "median", "sd", "p10", "p90")
#: Share cut from each end for a trimmed mean (of a session's pixels, of a group's sessions).
TRIM = 0.1
#: Columns that name a session rather than group sessions.
IDENTITY_COLUMNS = ("session", "date", "status", "error", "seconds", "pixels")


def reconstructed(rows: Sequence[dict]) -> list[dict]:
    """The rows with maps' statistics (a session reconstructed now or before; not a calibration alone)."""
    return [r for r in rows if r.get("status") in ("done", "skipped") and "pixels" in r]


def trimmed_mean(values: np.ndarray, trim: float = TRIM) -> float:
    """The mean of the finite ``values`` (1-D) without the ``trim`` share at each end (rounded down; NaN
    when none is finite)."""
    values = np.asarray(values, dtype=np.float64).ravel()
    values = np.sort(values[np.isfinite(values)])
    if values.size == 0:
        return math.nan
    cut = int(trim * values.size)
    return float(values[cut:values.size - cut].mean())


def session_summary(reconstruction: str | Path) -> dict[str, float]:
    """One session's row: ``pixels`` (scored) and ``<map>_<stat>`` for each of ``MAPS`` × ``STATS``, read
    from the reconstruction folder's ``maps.exr`` (its ``flags`` decide the scored pixels)."""
    import torch  # noqa: PLC0415 (the study table itself needs no torch)

    from ..demo import scored_pixels  # noqa: PLC0415
    from ..formats.exr import read_exr  # noqa: PLC0415

    channels, _ = read_exr(Path(reconstruction) / "maps.exr")
    keep = scored_pixels(torch.as_tensor(np.asarray(channels["flags"])).to(torch.int64)).numpy()
    row: dict[str, float] = {"pixels": int(keep.sum())}
    for name in MAPS:
        values = np.asarray(channels[name], dtype=np.float64)[keep]
        values = values[np.isfinite(values)]
        empty = values.size == 0
        row[f"{name}_trimmed_mean"] = trimmed_mean(values)
        row[f"{name}_median"] = math.nan if empty else float(np.median(values))
        row[f"{name}_sd"] = math.nan if values.size < 2 else float(values.std(ddof=1))
        row[f"{name}_p10"] = math.nan if empty else float(np.percentile(values, 10))
        row[f"{name}_p90"] = math.nan if empty else float(np.percentile(values, 90))
    return row


def grouping_columns(rows: Sequence[dict], asked: Sequence[str] = ()) -> list[str]:
    """The columns the study is grouped by: ``asked`` (each must be a column), else every column that is
    not an identity or a map's and puts at least two sessions together without putting all in one."""
    columns = [c for c in (rows[0] if rows else {}) if c not in IDENTITY_COLUMNS and not is_map_column(c)]
    if asked:
        missing = [c for c in asked if c not in columns]
        if missing:
            from ..formats.errors import InputError  # noqa: PLC0415

            raise InputError(f"--group {', '.join(missing)}: not a column of the study (its columns: {', '.join(columns)})")
        return list(asked)
    return [c for c in columns if 1 < len({str(r[c]) for r in rows}) < len(rows)]


def group_statistics(rows: Sequence[dict], column: str) -> dict[str, dict]:
    """Per value of ``column``: ``sessions`` and, per map, ``trimmed_mean`` of the sessions' trimmed means
    and ``sd`` across the sessions (NaN for one session)."""
    out: dict[str, dict] = {}
    for value in sorted({str(r[column]) for r in rows}):
        members = [r for r in rows if str(r[column]) == value]
        entry: dict = {"sessions": len(members)}
        for name in MAPS:
            means = np.array([float(r[f"{name}_trimmed_mean"]) for r in members])
            means = means[np.isfinite(means)]
            entry[name] = {"trimmed_mean": trimmed_mean(means), "sd": float(means.std(ddof=1)) if means.size > 1 else math.nan}
        out[value] = entry
    return out


def _session_means(rows: Sequence[dict]) -> tuple[list[str], np.ndarray, list[dict]]:
    """The maps that vary across sessions, the sessions' trimmed means of them ``(sessions, maps)`` and those
    sessions (a session with a map not finite is left out, not the map)."""
    table = np.array([[float(r[f"{n}_trimmed_mean"]) for n in MAPS] for r in rows], dtype=np.float64).reshape(len(rows), len(MAPS))
    finite = np.isfinite(table).all(axis=1)
    table, kept = table[finite], [r for r, f in zip(rows, finite) if f]
    varies = [j for j in range(len(MAPS)) if len(kept) and np.ptp(table[:, j]) > 0]
    return [MAPS[j] for j in varies], table[:, varies], kept


def correlations(rows: Sequence[dict]) -> dict:
    """Pearson's correlation of the maps' trimmed means across sessions (maps constant over the study and
    sessions with a map not finite left out; empty below three sessions)."""
    names, table, kept = _session_means(rows)
    if len(kept) < 3 or len(names) < 2:
        return {"maps": names, "matrix": []}
    return {"maps": names, "matrix": np.corrcoef(table, rowvar=False).round(6).tolist()}


def principal_components(rows: Sequence[dict]) -> dict:
    """PCA of the sessions' standardised trimmed means: per component its share of the variance and its
    loadings on the maps, and each session's scores (empty below three sessions)."""
    names, table, kept = _session_means(rows)
    if len(kept) < 3 or not names:
        return {"maps": names, "explained": [], "loadings": [], "scores": {}}
    z = (table - table.mean(axis=0)) / table.std(axis=0, ddof=1)
    _, s, vt = np.linalg.svd(z, full_matrices=False)
    signs = np.where(vt[np.arange(len(vt)), np.abs(vt).argmax(axis=1)] < 0, -1.0, 1.0)  # largest loading positive
    vt = vt * signs[:, None]
    variance = s**2
    return {"maps": names, "explained": (variance / variance.sum()).round(6).tolist(), "loadings": vt.round(6).tolist(),
            "scores": {str(r["session"]): (z[i] @ vt.T).round(6).tolist() for i, r in enumerate(kept)}}


def visit_changes(rows: Sequence[dict]) -> list[dict]:
    """Between consecutive visits (by ``date``, compared as text: ISO dates, YYYY-MM-DD) of the same
    ``subject`` and ``site`` (both given): each map's change of trimmed mean, absolute and relative to the
    earlier visit. Empty when the study lacks those columns."""
    if not rows or any(c not in rows[0] for c in ("subject", "site", "date")):
        return []
    visits: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        if str(r["subject"]) and str(r["site"]):  # a session without them is nobody's visit
            visits.setdefault((str(r["subject"]), str(r["site"])), []).append(r)
    out = []
    for (subject, site), seen in sorted(visits.items()):
        seen = sorted(seen, key=lambda r: (str(r["date"]), str(r["session"])))
        for before, after in zip(seen, seen[1:]):
            change = {n: float(after[f"{n}_trimmed_mean"]) - float(before[f"{n}_trimmed_mean"]) for n in MAPS}
            out.append({"subject": subject, "site": site, "from": str(before["session"]), "to": str(after["session"]),
                        "from_date": str(before["date"]), "to_date": str(after["date"]), "change": change,
                        "relative_change": {n: change[n] / abs(float(before[f"{n}_trimmed_mean"]))
                                            if float(before[f"{n}_trimmed_mean"]) else math.nan for n in MAPS}})
    return out


def study_record(rows: Sequence[dict], group_by: Sequence[str] = ()) -> dict:
    """``study.json``: the sessions counted by status, and over the reconstructed ones the groups of each
    grouping column, the correlations, the principal components and the visits' changes."""
    done = reconstructed(rows)
    columns = grouping_columns(done, group_by) if done else []
    return {
        "sessions": len(rows), "reconstructed": len(done),
        "failed": {str(r["session"]): r.get("error", "") for r in rows if r.get("status") == "failed"},
        "trim": TRIM, "pixels": "scored pixels (visible, no high residual, no hair)",
        "groups": {c: group_statistics(done, c) for c in columns},
        "correlations": correlations(done), "principal_components": principal_components(done),
        "visits": visit_changes(done),
    }


def write_study_table(path: str | Path, rows: Sequence[dict]) -> Path:
    """``study.csv``: one row per session, its columns first and then the maps' statistics (atomic)."""
    columns: list[str] = []
    for r in rows:
        columns += [c for c in r if c not in columns and not is_map_column(c)]
    columns += [f"{n}_{s}" for n in MAPS for s in STATS]
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns, extrasaction="ignore")
    writer.writeheader()
    for r in rows:
        writer.writerow({c: _cell(r.get(c)) for c in columns})
    return atomic_write(path, buffer.getvalue().encode())


def write_study_json(path: str | Path, record: dict) -> Path:
    """``study.json`` (atomic; NaN written as null)."""
    return atomic_write(path, (json.dumps(without_nan(record), indent=1) + "\n").encode())


def is_map_column(column: str) -> bool:
    """Whether ``column`` is one of the table's map statistics (``<map>_<stat>``)."""
    return any(column == f"{n}_{s}" for n in MAPS for s in STATS)


def _cell(value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return repr(value) if isinstance(value, float) else str(value)  # repr: the CSV reads back the same float


def without_nan(value):
    """``value`` (JSON-like) with every NaN float replaced by None (written as null)."""
    if isinstance(value, float):
        return None if math.isnan(value) else value
    if isinstance(value, dict):
        return {k: without_nan(v) for k, v in value.items()}
    if isinstance(value, list):
        return [without_nan(v) for v in value]
    return value
