"""Where a run's time goes, from a py-spy sampling profile: per demo step, the functions by inclusive and
by self time.

    py-spy record --format raw --rate 50 -o demo.txt -- skinlayers demo --size 256 -o /tmp/d
    python tests/bench/profile_summary.py demo.txt --rate 50 > profile.md

py-spy's raw format is one line per distinct stack: frames outermost first, ``;``-separated, each
``function (file:line)``, then a space and the number of samples. Time in torch's C++ kernels is
counted at the Python line that called them, which is the level this summary reports. A stack belongs to
the first demo step whose function it passes through (``STEPS``); the rest (imports, start-up, the CLI)
is ``other``. Stacks of other threads (``threading`` at their root: the progress bars' refresh, which
waits) are left out: they overlap the main thread's time.
"""

from __future__ import annotations

import argparse
import re
from collections import Counter, defaultdict
from pathlib import Path

#: The demo's steps, by the function each runs under (skinlayers/demo.py).
STEPS = {
    "simulate_session": "capture",
    "_calibrate": "calibrate",
    "_reconstruct": "reconstruct",
    "accuracy_against_truth": "report",
    "_figure": "report",
    "_print_accuracy": "report",
}
#: Path prefixes that are the project's own code (a frame elsewhere is a library's).
PROJECT_DIRS = ("acquire/", "calibration/", "formats/", "model/", "reconstruct/", "skinlayers/")
_FRAME = re.compile(r"^(?P<func>.*) \((?P<file>.*?)(?::(?P<line>\d+))?\)$")


def parse(path: Path) -> list[tuple[list[tuple[str, str]], int]]:
    """Stacks ``[(function, short file), …]`` (outermost first) with their sample counts."""
    stacks = []
    for raw in path.read_text().splitlines():
        if not raw.strip():
            continue
        stack, _, count = raw.rpartition(" ")
        frames = []
        for text in stack.split(";"):
            match = _FRAME.match(text.strip())
            if match is None:  # the process/thread header py-spy may put first
                continue
            frames.append((match["func"], short_file(match["file"])))
        if frames and frames[0][1].startswith("threading.py"):
            continue
        stacks.append((frames, int(count)))
    return stacks


def short_file(path: str) -> str:
    """``…/site-packages/torch/nn/functional.py`` → ``torch/nn/functional.py``; the project's files from its root."""
    for marker in ("site-packages/", "dist-packages/", "lib/python3."):
        if marker in path:
            path = path.split(marker, 1)[1]
            return path.split("/", 1)[1] if marker == "lib/python3." else path
    for root in PROJECT_DIRS:
        if f"/{root}" in path:
            return root + path.split(f"/{root}", 1)[1]
    return path


def is_project(file: str) -> bool:
    return file.startswith(PROJECT_DIRS) and not file.startswith("skinlayers/cli.py")


def step_of(frames: list[tuple[str, str]]) -> str:
    for func, file in frames:
        if file.startswith("skinlayers/demo.py") and func in STEPS:
            return STEPS[func]
    return "other"


def summarise(stacks, rate_hz: float, top: int) -> str:
    """A markdown report: seconds per step; per step the project functions by inclusive time and the
    innermost frames (self time, where the samples were taken)."""
    per_step = Counter()
    inclusive: dict[str, Counter] = defaultdict(Counter)
    own: dict[str, Counter] = defaultdict(Counter)
    for frames, count in stacks:
        step = step_of(frames)
        per_step[step] += count
        seen = set()
        for func, file in frames:
            key = f"{file.split(':')[0]}::{func}"
            if is_project(file) and key not in seen:
                seen.add(key)
                inclusive[step][key] += count
        if frames:
            func, file = frames[-1]
            own[step][f"{file}::{func}"] += count
    total = sum(per_step.values())
    lines = [f"Samples: {total} at {rate_hz:g} Hz = {total / rate_hz:.1f} s.", "", "| step | seconds | share |", "|---|---:|---:|"]
    for step, count in per_step.most_common():
        lines.append(f"| {step} | {count / rate_hz:.1f} | {100 * count / total:.0f}% |")
    for step, count in per_step.most_common():
        lines += ["", f"### {step}: {count / rate_hz:.1f} s", "", "| project function (inclusive) | s | share of step |", "|---|---:|---:|"]
        for key, n in inclusive[step].most_common(top):
            lines.append(f"| `{key}` | {n / rate_hz:.1f} | {100 * n / count:.0f}% |")
        lines += ["", "| innermost Python frame (self) | s | share of step |", "|---|---:|---:|"]
        for key, n in own[step].most_common(top):
            lines.append(f"| `{key}` | {n / rate_hz:.1f} | {100 * n / count:.0f}% |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("profile", type=Path, help="py-spy --format raw output")
    parser.add_argument("--rate", type=float, default=100.0, help="py-spy's --rate (samples per second)")
    parser.add_argument("--top", type=int, default=15, help="rows per table")
    args = parser.parse_args()
    print(summarise(parse(args.profile), args.rate, args.top), end="")


if __name__ == "__main__":
    main()
