"""Docstrings and comments say what and why; measured figures live in docs/ (issue 43).

Scans the comments and docstrings of every module of the packages for a quoted measurement (a timing,
a speed-up, "X against Y", "from X to Y", a peak memory, "measured … N", a percentage claim), a
paragraph at a time: a run of consecutive ``#`` lines, or a docstring paragraph between blank lines.
The heuristic is the issue-43 audit's (``runs/audit43``), tightened where its wording caught a
definition ("measured in units of"). Citations (``DWRR08 §6.3``, ``Eq. 9``, ``Table 2``) and ``code``
spans are removed before matching. A figure the code needs to explain itself goes to the docs page of
its module (under "Figures from the code"; calibration: docs/calibration.md), and the comment points
there. Stdlib only, no imports of the packages.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("acquire", "calibration", "formats", "model", "reconstruct", "skinlayers")

_N = r"(?<![A-Za-z\d_.])\d+(?:,\d{3})*(?:\.\d+)?"  # 4,096  0.075  26
_RNG = rf"{_N}(?:\s?[–-]\s?{_N})?"  # 0.5–1.4
#: A paragraph that matches any of these quotes a measurement.
STRONG = {
    "timing": re.compile(
        rf"(?<![/\d.]){_RNG}\s?(?:ms|µs|s|seconds?|min|minutes?|hours?)\b(?![⁻¹²])"
        r"|\b(?:about|under|within) (?:a|one|two|\w+ to \w+) (?:minutes?|seconds?|hours?)\b"),
    "speed": re.compile(
        rf"{_RNG}\s?×\s?(?:faster|slower|longer|shorter)\b|\b(?:an order of magnitude|several times) (?:faster|slower)\b",
        re.I),
    "versus": re.compile(rf"{_N}\s?(?:%|ms|px|×|σ|raw px|cube px)?\s+against\s+[+−-]?{_N}"),
    "before_after": re.compile(rf"\bfrom\s+{_N}\s?\S{{0,8}}\s+to\s+{_N}\b|(?<![`\d]){_N}\s?(?:ms)?\s?→\s?{_N}(?![`\d])"),
    "memory": re.compile(rf"\b(?:peaked|asked for|took)\b[^.]*?{_N}\s?(?:kB|MB|GB|GiB|MiB)\b|measured[^.]*?{_N}\s?(?:kB|MB|GB)\b"),
    # "measured in units of 1/σt′" defines a length scale, not a result
    "measured_n": re.compile(rf"\b[Mm]easure[sd]?\b(?! in units\b)[^.;]*?{_N}|{_N}[^.;]*?\bmeasured\b"),
    "pct_claim": re.compile(
        rf"\b(?:within|off by|up to|by up to|short of|against|saved)\s[+±~−-]?{_RNG}\s?%|{_RNG}\s?% (?:too|worse|higher|lower|low|dark)\b"),
    "result_verb": re.compile(rf"\b(?:took|peaked|saved|came out|read as)\b\s[^.;]*?{_N}|\b(?:was|were) {_N}\b"),
}
#: Provenance words: they flag a paragraph only together with a FIGURE.
WEAK = re.compile(
    r"\b[Mm]easured\b(?! in units\b)|\bon (?:a |the )?(?:flat|clean|noise-free|full-size|simulated|synthetic)\b|\bin our (?:tests|synthetic)\b"
    r"|\b\d[\d,]* simulated (?:spectra|sessions)\b|\bon NIST\b|\bon (?:one|two|\d+) (?:CPU )?(?:cores|threads)\b"
    r"|\(simulated sessions\)")
FIGURE = re.compile(rf"{_N}\s?(?:%|×|px|σ)|\b\d\.\d+\b")
_CODE = re.compile(r"``[^`]*``")
_CITATION = re.compile(r"(?:§|Fig\. |Eq\. |Table |DWRR08 )[\d.–, ]+")

#: (file, the paragraph's first words) → why its figures are not the project's measurements. Keep it short:
#: an entry that no longer matches a flagged paragraph fails ``test_allowlist_is_current``.
ALLOWLIST = {
    ("acquire/hardware/fw102c.py", "* Whether the prompt after"):
        "Bev.Instruments' measured half-turn time of the wheel: a cited third party's figure",
    ("acquire/hardware/virtual_fw102c.py", "Behaviour, as"):
        "the wheel's manual and Bev.Instruments' published timings: cited third-party figures",
    ("acquire/hardware/simdevices.py", "It reports exactly the listed value"):
        "a tolerance setting (1/32 stop) and its arithmetic, not a result",
    ("calibration/raw.py", "**Superpixel.**"):
        "512 → 256 is the window's resampling (image sizes), not a before/after result",
    ("reconstruct/levels/unknowns.py", "Parameters. Each map"):
        "the reparameterisation's arithmetic (C_m's range mapped onto x), not a result",
    ("reconstruct/settings.py", "Node spacing (mm) per map"):
        "the defaults themselves, pointing to the docs that hold their measurements",
}


def paragraphs(source: str) -> list[list[tuple[int, str]]]:
    """(line, text) runs: consecutive ``#`` comment lines, and each docstring's paragraphs."""
    out: list[list[tuple[int, str]]] = []
    run: list[tuple[int, str]] = []
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type != tokenize.COMMENT:
            continue
        if run and run[-1][0] == tok.start[0] - 1:
            run.append((tok.start[0], tok.string))
        else:
            if run:
                out.append(run)
            run = [(tok.start[0], tok.string)]
    if run:
        out.append(run)
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) or not node.body:
            continue
        first = node.body[0]
        if not (isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str)):
            continue
        para: list[tuple[int, str]] = []
        for i, line in enumerate(first.value.value.splitlines()):
            if line.strip():
                para.append((first.lineno + i, line))
            elif para:
                out.append(para)
                para = []
        if para:
            out.append(para)
    return out


def _prose(text: str) -> str:
    """Text as matched: ``code`` spans and citation numbers removed."""
    return _CITATION.sub("REF ", _CODE.sub("``…``", text))


def kinds_of(text: str) -> list[str]:
    """The kinds of measured figure a paragraph's text quotes (empty: none)."""
    text = _prose(text)
    kinds = [k for k, r in STRONG.items() if r.search(text)]
    if not kinds and WEAK.search(text) and FIGURE.search(text):
        kinds = ["provenance+figure"]
    return kinds


def findings(source: str, rel: str) -> list[tuple[str, int, list[str], str]]:
    """(file, line, kinds, paragraph text) for each paragraph of ``source`` that quotes a figure."""
    found = []
    for para in paragraphs(source):
        text = " ".join(t.strip().lstrip("#:").strip() for _, t in para)
        kinds = kinds_of(text)
        if not kinds:
            continue
        line = next((ln for ln, t in para if kinds_of(t.strip().lstrip("#:").strip()) or WEAK.search(_prose(t))), para[0][0])
        found.append((rel, line, kinds, text))
    return found


def _allowed(rel: str, text: str) -> tuple[str, str] | None:
    return next((key for key in ALLOWLIST if key[0] == rel and text.startswith(key[1])), None)


def _scan() -> tuple[list[str], set[tuple[str, str]]]:
    problems, used = [], set()
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            for _, line, kinds, text in findings(path.read_text(encoding="utf-8"), rel):
                key = _allowed(rel, text)
                if key:
                    used.add(key)
                else:
                    problems.append(f"{rel}:{line} [{','.join(kinds)}] {text[:200]}")
    return problems, used


def test_no_measured_figures_in_comments_or_docstrings():
    problems, _ = _scan()
    assert not problems, (
        "comments and docstrings quote measured figures; move them to docs/ (the module's page, "
        "'Figures from the code') and point there:\n" + "\n".join(problems))


def test_allowlist_is_current():
    _, used = _scan()
    stale = sorted(set(ALLOWLIST) - used)
    assert not stale, f"allowlist entries that match no flagged paragraph any more: {stale}"


SNIPPET = '''
def jacobian(x):
    """Reverse mode, measured 4.5× faster than forward mode here."""
    # 26 against 60 ms for 4,096 rows
    y = x
    # DWRR08 §6.3, Eq. 9
    return y
'''


def test_the_scan_can_fail():
    found = {line: kinds for _, line, kinds, _ in findings(SNIPPET, "snippet.py")}
    assert 3 in found and "speed" in found[3], found  # the docstring
    assert 4 in found and "versus" in found[4] and "timing" in found[4], found  # the comment
    assert 6 not in found, found  # a citation is not a measurement
    assert len(found) == 2, found


def test_what_is_not_a_measurement():
    for text in ("DWRR08 §6.3, Eq. 9", "Fresnel at normal incidence, Table 2's skins",
                 "lengths are measured in units of 1/σt′ (the similarity relation)",
                 "lengths measured in units of 1/σt′ under the 7.5-mm window",
                 "docs/calibration.md, \"From calibration/_edge_model.py\""):
        assert not kinds_of(text), text
    for text in ("took 0.5–1.4 s", "10⁷ photons peaked 282 MB", "from 0.53 to 0.33 raw px",
                 "within 0.6% over Table 2", "measured on noise-free frames: 0.2 px"):
        assert kinds_of(text), text
