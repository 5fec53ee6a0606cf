"""The README names only what exists: every `mateqa COMMAND ...` line of its code blocks and
inline code parses with the real parser (each option is one of that command's), every option it
names in passing is one of some command's or of the other tools it shows, every `make TARGET`
is a target of the Makefile, and every file of the repository it names is there."""

from __future__ import annotations

import argparse
import re
import shlex
import sys
from pathlib import Path

import pytest

from flows.cli import _parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
# Options of other programs the README shows: prefect's CLI, docker compose, the benchmarks
# and the CadQuery script of an export.
OTHER_TOOLS = {"--param", "--watch", "--build", "--prefect-file", "--pool", "--scale",
               "--views", "--pairs", "--library", "--categories", "--repeat", "--repeats",
               "--json", "--perturb", "--list", "--seconds"}


def _fenced(text: str) -> list[str]:
    """The lines of the fenced code blocks."""
    return [line for block in re.findall(r"```[a-z]*\n(.*?)```", text, re.S)
            for line in block.splitlines()]


def _inline(text: str) -> list[str]:
    """The inline code spans outside the fenced blocks."""
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    return re.findall(r"`([^`\n]+)`", prose)


def mateqa_lines(text: str) -> list[str]:
    """Each `mateqa ...` command the README shows: block lines (with their indented
    continuation lines and trailing backslashes) and inline spans, comments removed."""
    lines, out = _fenced(text), []
    for i, line in enumerate(lines):
        words = line.split("#")[0].strip()
        if not re.match(r"(\S*/)?mateqa \w", words):
            continue
        j = i + 1
        while j < len(lines) and (words.endswith("\\") or re.match(r"\s+[\[-]", lines[j])):
            words = words.rstrip("\\") + " " + lines[j].split("#")[0].strip()
            j += 1
        out.append(words)
    out += [span for span in _inline(text) if re.match(r"mateqa \w", span)]
    return out


def _argv(line: str) -> list[str]:
    """The words of a README command as a user would type them: optional parts given,
    the first of alternatives (A|B) taken, ellipses dropped."""
    words = shlex.split(re.sub(r"[\[\]]", " ", line.split("mateqa", 1)[1]))
    return [w.split("|")[0] for w in words if w not in ("...", "|")]


def _commands() -> dict[str, argparse.ArgumentParser]:
    return dict(_parser()._subparsers._group_actions[0].choices)  # type: ignore[union-attr]


def test_every_mateqa_command_of_the_readme_parses() -> None:
    lines = mateqa_lines(README.read_text())
    assert len(lines) >= 10  # the quick start and the reference are found
    commands, bad = _commands(), []
    for line in lines:
        argv = _argv(line)
        if argv in (["COMMAND", "--help"], ["COMMAND"]):
            continue
        sub = commands.get(argv[0])
        if sub is None:
            bad.append(f"{line}: no command {argv[0]!r}")
            continue
        unknown = [w for w in argv if w.startswith("--") and
                   w.split("=")[0] not in sub._option_string_actions]
        if unknown:
            bad.append(f"{line}: `mateqa {argv[0]}` has no {', '.join(unknown)}")
            continue
        if len(argv) == 1:  # the command named in prose
            continue
        try:
            _parser().parse_args(argv)
        except SystemExit:
            bad.append(f"{line}: does not parse")
    assert not bad, "\n".join(bad)


def test_every_option_the_readme_names_is_a_command_s_or_another_tool_s() -> None:
    known = {opt for sub in _commands().values() for opt in sub._option_string_actions}
    named = {opt for span in _inline(README.read_text()) + _fenced(README.read_text())
             for opt in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", span)}
    assert named - known - OTHER_TOOLS == set()


def test_every_make_target_the_readme_names_is_in_the_makefile() -> None:
    text = README.read_text()
    targets = set(re.findall(r"^([a-z][\w-]*):", (ROOT / "Makefile").read_text(), re.M))
    named = {m for span in _inline(text) + _fenced(text)
             for m in re.findall(r"^\s*make ([a-z][\w-]*)", span)}
    assert named, "the README names no make target"
    assert named - targets == set()


def _repository_paths(text: str) -> set[str]:
    top = {p.name for p in ROOT.iterdir() if not p.name.startswith(".")}
    paths = set()
    for span in _inline(text):
        word = span.split("::")[0].rstrip("/")
        if " " in word or "<" in word or "*" in word:
            continue
        if word.split("/")[0] in top or re.fullmatch(r"[A-Z_]+\.md", word):
            paths.add(word)
    return paths


def test_every_repository_file_the_readme_names_exists() -> None:
    paths = _repository_paths(README.read_text())
    assert "docs/ARCHITECTURE.md" in paths and "bench/README.md" in paths
    missing = [p for p in sorted(paths)
               if not (ROOT / p).exists() and not list(ROOT.glob(f"**/{p}"))]
    assert not missing


@pytest.mark.parametrize("line, problem", [
    ("mateqa serve --tol contact_mm=0.2", "has no --tol"),
    ("mateqa nightly --no-such-option", "has no --no-such-option"),
    ("mateqa train sideways", "does not parse"),
])
def test_the_check_sees_a_false_command(line: str, problem: str,
                                        monkeypatch: pytest.MonkeyPatch,
                                        tmp_path: Path) -> None:
    readme = tmp_path / "README.md"
    readme.write_text(README.read_text() + f"\n```\n{line}\n```\n")
    monkeypatch.setattr(sys.modules[__name__], "README", readme)
    with pytest.raises(AssertionError, match=re.escape(problem)):
        test_every_mateqa_command_of_the_readme_parses()
