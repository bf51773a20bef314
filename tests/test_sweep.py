"""The analyses' shared machinery: the Pareto front on constructed points, the resumable table, the
peak-memory sampler."""

from __future__ import annotations

import csv
import math
import mmap
import time

import pytest
import torch

from skinlayers.analyses.sweep import PeakMemory, SweepTable, pareto_front, time_to_front


def test_pareto_front_on_a_constructed_example():
    #          fast+bad  slow+good  dominated  tie(a)   tie(b)   slower, no better  nan
    cost = [1.0, 10.0, 5.0, 3.0, 3.0, 12.0, math.nan]
    error = [0.9, 0.1, 0.5, 0.4, 0.4, 0.1, 0.05]
    front = pareto_front(cost, error)
    # the two equal points are both on the front; (5, 0.5) is dominated by (3, 0.4); (12, 0.1) by (10, 0.1)
    assert front == [True, True, False, True, True, False, False]


def test_a_dominated_default_and_its_distance_to_the_front():
    cost = [2.0, 1.0, 4.0]  # the default (index 0) is slower than index 1 and no more accurate
    error = [0.3, 0.3, 0.1]
    assert pareto_front(cost, error) == [False, True, True]
    assert time_to_front(cost, error, 0) == pytest.approx(2.0)
    assert time_to_front(cost, error, 1) == pytest.approx(1.0)
    assert time_to_front(cost, error, 2) == pytest.approx(1.0)  # nothing as accurate is faster


def test_one_point_and_all_equal_points_are_the_front():
    assert pareto_front([1.0], [1.0]) == [True]
    assert pareto_front([2.0, 2.0, 2.0], [1.0, 1.0, 1.0]) == [True, True, True]


def test_a_rerun_after_an_interruption_measures_only_the_missing_rows(tmp_path):
    cases = [{"config": c, "scene": s} for c in ("a", "b", "c") for s in ("x", "y")]
    measured = []

    def measure(case):
        if len(measured) == 4:
            raise KeyboardInterrupt  # the user stops it after four rows
        measured.append((case["config"], case["scene"]))
        return {"value": 0.5 * len(measured)}

    path = tmp_path / "t.csv"
    with pytest.raises(KeyboardInterrupt):
        SweepTable(path, ["config", "scene", "value"], ["config", "scene"]).run(cases, measure, say=lambda _: None)
    with path.open() as f:
        assert len(list(csv.DictReader(f))) == 4  # every finished row is on disk
    measured.clear()
    table = SweepTable(path, ["config", "scene", "value"], ["config", "scene"])
    table.run(cases, lambda case: measured.append((case["config"], case["scene"])) or {"value": 9.0}, say=lambda _: None)
    assert measured == [("c", "x"), ("c", "y")]
    assert [(r["config"], r["scene"]) for r in table.rows] == [(c["config"], c["scene"]) for c in cases]
    assert table.run(cases, lambda case: pytest.fail("nothing is left to measure"), say=lambda _: None).total == 0


def test_a_table_of_other_columns_is_refused(tmp_path):
    path = tmp_path / "t.csv"
    SweepTable(path, ["a", "b"], ["a"]).append({"a": 1, "b": 2})
    with pytest.raises(ValueError, match="columns"):
        SweepTable(path, ["a", "c"], ["a"])
    with pytest.raises(ValueError, match="columns the table does not"):
        SweepTable(path, ["a", "b"], ["a"]).append({"a": 1, "z": 3})


def test_progress_says_what_is_left(tmp_path):
    said = []
    SweepTable(tmp_path / "t.csv", ["k", "v"], ["k"]).run([{"k": i} for i in range(3)], lambda c: {"v": 1}, say=said.append,
                                                         estimate_s=lambda c: 1.0)
    assert said[0].startswith("[1/3]") and "left" in said[1] and said[-1].startswith("    ") and "3/3 done" in said[-1]


def test_peak_memory_sees_a_block_that_allocates():
    with PeakMemory() as small:
        torch.zeros(10)
    with PeakMemory() as big:
        # 64 MB of fresh pages, each touched, held a while (the sampler reads every 5 ms). An anonymous map,
        # not torch.ones: a tensor may reuse pages the allocator still holds from earlier tests.
        block = mmap.mmap(-1, 64 * 2**20)
        block.write(b"\1" * len(block))
        time.sleep(0.1)
        block.close()
    assert big.peak_mb > 40.0 and big.peak_mb > small.peak_mb + 30.0


def test_an_analysis_device_is_cpu_cuda_or_auto_and_cuda_only_where_there_is_one():
    from skinlayers.formats.errors import InputError
    from skinlayers.analyses.sweep import analysis_device

    assert analysis_device("cpu") == "cpu"
    assert analysis_device("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(InputError, match="expected cpu, cuda or auto"):
        analysis_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(InputError, match="no CUDA device"):
            analysis_device("cuda")
