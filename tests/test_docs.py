"""The documentation keeps its shape (issue 43): a short README that links the reference pages, every
command and option of the ``skinlayers`` command in docs/cli.md, and no broken relative link."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
README = ROOT / "README.md"

#: The README is the way in; the reference lives in docs/.
README_MAX_LINES = 150
#: The reference pages every reader must be able to reach from the README.
REFERENCE_PAGES = ("tutorial.md", "cli.md", "formats.md", "hardware.md", "accuracy.md", "speed.md", "limits.md")

_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)


def _markdown_files() -> list[Path]:
    return [README, *sorted(DOCS.glob("*.md"))]


def _links(text: str) -> list[str]:
    """The targets of Markdown links and images, code blocks left out."""
    return _LINK.findall(_FENCE.sub("", text))


def _relative_targets(text: str) -> list[str]:
    """Link targets that name a file here: no scheme (http:, mailto:), no pure #anchor; #… stripped."""
    found = []
    for target in _links(text):
        if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target) or target.startswith("#"):
            continue
        found.append(target.split("#", 1)[0])
    return found


def _cli_commands() -> dict[str, list[str]]:
    """Every command of the ``skinlayers`` app and its long options (``--help`` left out), from Typer."""
    import typer

    from skinlayers.cli import app

    group = typer.main.get_command(app)
    commands = {}
    for name, command in group.commands.items():
        options = []
        for param in command.params:
            # click's Option, or Typer's own (recent Typer vendors click: not a click.Option subclass)
            if getattr(param, "param_type_name", None) != "option":
                continue
            for opt in [*param.opts, *getattr(param, "secondary_opts", [])]:
                if opt.startswith("--") and opt != "--help":
                    options.append(opt)
        commands[name] = options
    return commands


def _sections(text: str) -> list[tuple[str, str]]:
    """(heading, body) for each level-2 section of a Markdown text, code fences kept in the body."""
    parts = re.split(r"^## +(.*)$", text, flags=re.M)
    return [(parts[i].strip(), parts[i + 1]) for i in range(1, len(parts), 2)]


def _command_section(text: str, name: str) -> str | None:
    """The level-2 section of docs/cli.md whose heading names the command in backticks."""
    pattern = re.compile(rf"`(?:skinlayers )?{re.escape(name)}`")
    for heading, body in _sections(text):
        if pattern.search(heading):
            return body
    return None


def _missing_from_cli_doc(text: str, commands: dict[str, list[str]]) -> list[str]:
    missing = []
    for name, options in commands.items():
        body = _command_section(text, name)
        if body is None:
            missing.append(f"command {name}: no '## `skinlayers {name}`' section")
            continue
        for opt in options:
            if not re.search(rf"(?<![\w-]){re.escape(opt)}(?![\w-])", body):
                missing.append(f"{name} {opt}")
    return missing


def test_the_readme_is_short():
    lines = README.read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; the reference belongs in docs/"


def test_every_command_and_option_is_in_the_cli_reference():
    commands = _cli_commands()
    assert {"capture", "calibrate", "reconstruct", "render", "demo"} <= set(commands)
    assert {"--out", "--size", "--seed"} <= set(commands["demo"]), "the options were not found on the app"
    missing = _missing_from_cli_doc((DOCS / "cli.md").read_text(), commands)
    assert not missing, f"docs/cli.md lacks: {missing}"


def test_the_cli_check_sees_a_missing_option_and_command():
    """The check above can fail: an option named only in another command's section, and a command with
    no section, are both caught; a longer option does not stand in for a shorter one."""
    text = "## `skinlayers a`\n\n`--size-max`\n\n## `skinlayers b`\n\n`--size`\n"
    assert _missing_from_cli_doc(text, {"a": ["--size"], "b": ["--size"]}) == ["a --size"]
    assert _missing_from_cli_doc(text, {"c": []}) == ["command c: no '## `skinlayers c`' section"]


@pytest.mark.parametrize("path", _markdown_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(path):
    broken = [t for t in _relative_targets(path.read_text()) if t and not (path.parent / t).exists()]
    assert not broken, f"{path.relative_to(ROOT)}: links to missing files {broken}"


def test_the_link_check_sees_links_and_skips_the_rest():
    text = (
        "See [a](docs/a.md#x), ![fig](docs/figures/f.png \"title\"), [web](https://example.org/x.md),\n"
        "[here](#anchor) and [nested [b]](b.md).\n```\n[not a link](inside/code.md)\n```\n"
    )
    assert _relative_targets(text) == ["docs/a.md", "docs/figures/f.png", "b.md"]


def test_the_readme_links_every_reference_page():
    targets = {Path(t).as_posix() for t in _relative_targets(README.read_text())}
    missing = [page for page in REFERENCE_PAGES if f"docs/{page}" not in targets]
    assert not missing, f"README.md does not link {missing}"
    assert all((DOCS / page).is_file() for page in REFERENCE_PAGES)
