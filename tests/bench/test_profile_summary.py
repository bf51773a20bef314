"""The profile summary attributes samples to the demo's steps and to project functions (a constructed
py-spy raw profile; runs in the default suite: it is fast)."""

from __future__ import annotations

from profile_summary import parse, summarise

RAW = """\
<module> (/x/bin/skinlayers:8);demo (/repo/skinlayers/demo.py:221);simulate_session (/repo/skinlayers/demo.py:258);render (/repo/model/renderer.py:10);_symmetric_sums (/repo/model/blur.py:5) 30
<module> (/x/bin/skinlayers:8);demo (/repo/skinlayers/demo.py:221);_reconstruct (/repo/skinlayers/demo.py:280);render (/repo/model/renderer.py:10);pad (/venv/lib/python3.11/site-packages/torch/nn/functional.py:4) 20
<module> (/x/bin/skinlayers:8);demo (/repo/skinlayers/demo.py:221);_reconstruct (/repo/skinlayers/demo.py:280);solve (/repo/reconstruct/schur.py:3) 10
Thread._bootstrap (/usr/lib/python3.11/threading.py:1002);Condition.wait (/usr/lib/python3.11/threading.py:320) 99
<module> (/x/bin/skinlayers:8);<module> (/repo/model/__init__.py:1) 5
"""


def test_samples_go_to_their_step_and_function(tmp_path):
    path = tmp_path / "raw.txt"
    path.write_text(RAW)
    stacks = parse(path)
    assert sum(count for _, count in stacks) == 65  # the waiting thread's samples are left out
    report = summarise(stacks, rate_hz=10.0, top=5)
    assert "| capture | 3.0 | 46% |" in report
    assert "| reconstruct | 3.0 | 46% |" in report
    assert "| other | 0.5 | 8% |" in report
    assert "| `model/renderer.py::render` | 2.0 | 67% |" in report  # inclusive, within reconstruct
    assert "| `torch/nn/functional.py::pad` | 2.0 | 67% |" in report  # self time, a library's frame
    assert "threading" not in report
