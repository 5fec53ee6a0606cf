"""The README and the pages of docs/ name only what exists: every `mateqa COMMAND ...` line of
their code blocks and inline code parses with the real parser (each option is one of that
command's), every option they name in passing is one of some command's or of the other tools
they show, every `make TARGET` is a target of the Makefile, and every file of the repository
they name or link to is there. The README stays short enough to read."""

from __future__ import annotations

import argparse
import re
import shlex
from pathlib import Path

import pytest

from flows.cli import _parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]
README_MAX_LINES = 260
# Options of other programs the pages show: prefect's CLI, docker compose, systemctl, the
# benchmarks, the packed trainer and the CadQuery script of an export.
OTHER_TOOLS = {"--param", "--watch", "--build", "--prefect-file", "--pool", "--scale",
               "--views", "--pairs", "--library", "--categories", "--repeat", "--repeats",
               "--json", "--perturb", "--list", "--seconds", "--rm", "--type", "--now",
               "--seeds"}



def _page_id(page: Path) -> str:
    return str(page.relative_to(ROOT))


def _fenced(text: str) -> list[str]:
    """The lines of the fenced code blocks."""
    return [line for block in re.findall(r"```[a-z]*\n(.*?)```", text, re.S)
            for line in block.splitlines()]


def _inline(text: str) -> list[str]:
    """The inline code spans outside the fenced blocks."""
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    return re.findall(r"`([^`\n]+)`", prose)


def mateqa_lines(text: str) -> list[str]:
    """Each `mateqa ...` command a page shows: block lines (with their indented continuation
    lines and trailing backslashes) and inline spans, comments removed."""
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
    """The words of a command as a user would type them: optional parts given, the first of
    alternatives (A|B) taken, ellipses dropped."""
    words = shlex.split(re.sub(r"[\[\]]", " ", line.split("mateqa", 1)[1]))
    return [w.split("|")[0] for w in words if w not in ("...", "|")]


def _choices(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """A parser's sub-commands (none when it has none)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _commands() -> dict[str, argparse.ArgumentParser]:
    return _choices(_parser())


def _all_parsers() -> list[argparse.ArgumentParser]:
    """Every command's parser, and its sub-commands' (``schedule add``, ...)."""
    todo, out = list(_commands().values()), []
    while todo:
        parser = todo.pop()
        out.append(parser)
        todo += _choices(parser).values()
    return out


def _command_problem(line: str, commands: dict[str, argparse.ArgumentParser]) -> str:
    """What is wrong with one `mateqa ...` line ("" when nothing)."""
    argv = _argv(line)
    sub = commands.get(argv[0])
    if sub is None:
        return f"{line}: no command {argv[0]!r}"
    depth = 1
    while len(argv) > depth and argv[depth] in _choices(sub):  # `schedule add`, ...
        sub, depth = _choices(sub)[argv[depth]], depth + 1
    unknown = [w for w in argv if w.startswith("--") and
               w.split("=")[0] not in sub._option_string_actions]
    if unknown:
        return f"{line}: `mateqa {' '.join(argv[:depth])}` has no {', '.join(unknown)}"
    if _named(argv[depth:], sub):
        return ""
    try:
        _parser().parse_args(argv)
    except SystemExit:
        return f"{line}: does not parse"
    return ""


def _named(words: list[str], sub: argparse.ArgumentParser) -> bool:
    """Whether a command is only named (in prose: `mateqa schedule`, `mateqa ship STAGE`,
    `mateqa thresholds calibrate`) rather than shown as typed: no option, and every word left a
    placeholder or one of its positional choices."""
    choices = {c for a in sub._actions if not a.option_strings and a.choices for c in a.choices}
    return all(w.isupper() or w in choices for w in words)


def check_commands(page: Path) -> None:
    lines = mateqa_lines(page.read_text())
    commands, bad = _commands(), []
    for line in lines:
        argv = _argv(line)
        if argv in (["COMMAND", "--help"], ["COMMAND"]):
            continue
        problem = _command_problem(line, commands)
        if problem:
            bad.append(problem)
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("page", PAGES, ids=_page_id)
def test_every_mateqa_command_parses(page: Path) -> None:
    check_commands(page)


def test_the_readme_shows_the_commands_a_user_starts_with() -> None:
    argvs = [_argv(line) for line in mateqa_lines(README.read_text())]
    for command in ("nightly", "inspect", "thresholds", "schedule"):
        assert any(argv[0] == command for argv in argvs), command


@pytest.mark.parametrize("page", PAGES, ids=_page_id)
def test_every_option_named_is_a_command_s_or_another_tool_s(page: Path) -> None:
    known = {opt for sub in _all_parsers() for opt in sub._option_string_actions}
    text = page.read_text()
    named = {opt for span in _inline(text) + _fenced(text)
             for opt in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*[a-z0-9]", span)}
    assert named - known - OTHER_TOOLS == set()


def _make_targets(text: str) -> set[str]:
    return {m for span in _inline(text) + _fenced(text)
            for m in re.findall(r"^\s*make ([a-z][\w-]*)", span)}


@pytest.mark.parametrize("page", PAGES, ids=_page_id)
def test_every_make_target_named_is_in_the_makefile(page: Path) -> None:
    targets = set(re.findall(r"^([a-z][\w-]*):", (ROOT / "Makefile").read_text(), re.M))
    assert _make_targets(page.read_text()) - targets == set()


def test_the_readme_s_two_commands_are_the_makefile_s_and_ci_runs_the_test_one() -> None:
    named = _make_targets(README.read_text())
    assert {"nightly", "test"} <= named
    ci = [line.strip() for line in (ROOT / ".ci/run").read_text().splitlines()
          if line.strip() and not line.startswith("#")]
    assert ci[-1] == "make test"


def _named_paths(page: Path) -> set[str]:
    """The repository files a page names in inline code, from the root."""
    top = {p.name for p in ROOT.iterdir() if not p.name.startswith(".")}
    paths = set()
    for span in _inline(page.read_text()):
        word = span.split("::")[0].rstrip("/")
        if " " in word or "<" in word or "*" in word:
            continue
        if word.split("/")[0] in top or re.fullmatch(r"[A-Z_]+\.md", word):
            paths.add(word)
    return paths


def _linked_paths(page: Path) -> set[Path]:
    """The files a page links to (relative links, from the page's folder)."""
    targets = re.findall(r"\]\(([^)\s#]+)(?:#[^)]*)?\)", page.read_text())
    return {(page.parent / t).resolve() for t in targets if not re.match(r"[a-z]+:", t)}


@pytest.mark.parametrize("page", PAGES, ids=_page_id)
def test_every_repository_file_named_exists(page: Path) -> None:
    # A bare file name (`MODEL_CARD.md`) may be anywhere in the repository.
    missing = [p for p in sorted(_named_paths(page)) if not (ROOT / p).exists()
               and not list(ROOT.glob(f"**/{p}"))]
    assert not missing


@pytest.mark.parametrize("page", PAGES, ids=_page_id)
def test_every_link_leads_to_a_file(page: Path) -> None:
    assert not sorted(str(p) for p in _linked_paths(page) if not p.exists())


def test_the_readme_names_its_neighbours() -> None:
    assert "bench/README.md" in _named_paths(README)
    assert {p.resolve() for p in PAGES if p != README} <= _linked_paths(README)


def test_the_readme_is_short_enough_to_read() -> None:
    assert len(README.read_text().splitlines()) <= README_MAX_LINES


@pytest.mark.parametrize("line, problem", [
    ("mateqa serve --tol contact_mm=0.2", "has no --tol"),
    ("mateqa nightly --no-such-option", "has no --no-such-option"),
    ("mateqa train sideways", "does not parse"),
    ("mateqa thresholds calibrate --out floors.toml", "does not parse"),
])
def test_the_check_sees_a_false_command(line: str, problem: str, tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text(README.read_text() + f"\n```\n{line}\n```\n")
    with pytest.raises(AssertionError, match=re.escape(problem)):
        check_commands(page)


def test_the_check_sees_a_broken_link(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text("[the reference](reference.md), [a site](https://example.org/x.md)")
    assert _linked_paths(page) == {tmp_path / "reference.md"}
    with pytest.raises(AssertionError):
        test_every_link_leads_to_a_file(page)
