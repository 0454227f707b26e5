"""The user documentation: README size and first commands, links, cited reports, commands that parse.

Fast and offline: reads files and builds the ``tidee`` argument parser; runs only the README's
in-process Python snippet.
"""

from __future__ import annotations

import argparse
import ast
import re
import shlex
from pathlib import Path

import pytest

from tests.support import REPO as SUPPORT_REPO
from tidee.cli import build_parser

ROOT = SUPPORT_REPO
README = ROOT / "README.md"
DOCS = ROOT / "docs"
EVAL = DOCS / "eval"
MAX_README_LINES = 200

# Built from pieces so that this file does not match itself.
HISTORY = re.compile(r"\b[Ss]" + r"ession #?\d+\b|\b[Ii]" + r"ssue #?\d+\b")
# A commit hash or a hash prefix: 7-40 hex digits with at least one letter and one digit.
HEX_ID = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```", re.S | re.M)
CODE_SPAN = re.compile(r"`([^`\n]+)`")
EVAL_MENTION = re.compile(r"docs/eval/([A-Za-z0-9_-]+)")
SOURCE_DIRS = ("server", "agent", "protocol", "viewer", "tidee", "tests", "examples")


def user_docs() -> list[Path]:
    """README.md and docs/*.md: what a user reads (the changelog is history and may name it)."""
    return [README, *sorted(DOCS.glob("*.md"))]


def linked_docs() -> list[Path]:
    return [*user_docs(), ROOT / "CHANGELOG.md", ROOT / "protocol" / "README.md"]


def fenced_blocks(text: str) -> list[tuple[str, str]]:
    return [(m.group(1).strip(), m.group(2)) for m in FENCE.finditer(text)]


def prose(text: str) -> str:
    """The text outside fenced code blocks (inline code spans kept)."""
    return FENCE.sub("", text)


def github_anchor(heading: str) -> str:
    """The anchor GitHub gives a Markdown heading."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    text = prose(path.read_text())
    return {github_anchor(m.group(1)) for m in re.finditer(r"^#{1,6}\s+(.+?)\s*$", text, re.M)}


def relative_links(path: Path) -> list[str]:
    return [
        t for t in LINK.findall(prose(path.read_text())) if not re.match(r"[a-z][a-z0-9+.-]*:", t)
    ]  # http:, https:, mailto:


# --- the README ---------------------------------------------------------------------------------


def test_readme_is_short() -> None:
    n = len(README.read_text().splitlines())
    assert n <= MAX_README_LINES, (
        f"README.md has {n} lines; keep it to {MAX_README_LINES} (the rest goes in docs/)"
    )


def test_readme_opens_with_the_two_commands() -> None:
    blocks = fenced_blocks(README.read_text())
    assert blocks, "README.md has no fenced code block"
    first = blocks[0][1]
    assert "make demo" in first and "make test" in first, f"README's first code block:\n{first}"


def test_readme_python_snippets_compile() -> None:
    for lang, code in fenced_blocks(README.read_text()):
        if lang == "python":
            ast.parse(code)


def test_readme_in_process_snippet_runs_as_written() -> None:
    """The snippets that need no running server are run exactly as the README prints them."""
    import subprocess
    import sys

    runnable = [
        code
        for lang, code in fenced_blocks(README.read_text())
        if lang == "python" and 'transport="inproc"' in code
    ]
    assert runnable, "README.md has no in-process Python snippet"
    for code in runnable:
        r = subprocess.run(
            [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
        )
        assert r.returncode == 0, f"README snippet failed:\n{code}\n{r.stderr[-2000:]}"


# --- no project history in user docs and code ---------------------------------------------------


def test_user_docs_carry_no_project_history() -> None:
    bad = []
    for path in [*user_docs(), ROOT / "protocol" / "README.md"]:
        for i, line in enumerate(path.read_text().splitlines(), 1):
            for pattern in (HISTORY, HEX_ID):
                if m := pattern.search(line):
                    bad.append(f"{path.relative_to(ROOT)}:{i}: {m.group(0)!r}")
    assert not bad, "history belongs in git and CHANGELOG.md:\n" + "\n".join(bad)


def test_source_carries_no_project_history() -> None:
    bad = []
    for top in SOURCE_DIRS:
        for path in sorted((ROOT / top).rglob("*.py")):
            for i, line in enumerate(path.read_text().splitlines(), 1):
                if m := HISTORY.search(line):
                    bad.append(f"{path.relative_to(ROOT)}:{i}: {m.group(0)!r}")
    assert not bad, "comments and docstrings state facts, not their history:\n" + "\n".join(bad)


# --- links and reports --------------------------------------------------------------------------


def test_relative_links_resolve() -> None:
    broken = []
    for path in linked_docs():
        for target in relative_links(path):
            file_part, _, anchor = target.partition("#")
            dest = (path.parent / file_part).resolve() if file_part else path
            if not dest.exists():
                broken.append(f"{path.relative_to(ROOT)}: {target} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                broken.append(f"{path.relative_to(ROOT)}: {target} (no heading #{anchor})")
    assert not broken, "broken links:\n" + "\n".join(broken)


def cited_reports() -> dict[str, list[str]]:
    """docs/eval folder name -> the user docs that cite it (by link or by path)."""
    cited: dict[str, list[str]] = {}
    for path in user_docs():
        names = set(EVAL_MENTION.findall(path.read_text()))
        for target in relative_links(path):
            dest = (path.parent / target.partition("#")[0]).resolve()
            if dest.is_relative_to(EVAL.resolve()) and dest != EVAL.resolve():
                names.add(dest.relative_to(EVAL.resolve()).parts[0])
        for name in names:
            cited.setdefault(name, []).append(str(path.relative_to(ROOT)))
    return cited


def test_every_report_folder_is_cited() -> None:
    cited = cited_reports()
    folders = sorted(p.name for p in EVAL.iterdir() if p.is_dir())
    uncited = [f for f in folders if f not in cited]
    assert not uncited, f"docs/eval folders no user doc cites (remove them, or cite them): {uncited}"


def test_every_cited_report_exists() -> None:
    missing = {name: where for name, where in cited_reports().items() if not (EVAL / name).is_dir()}
    assert not missing, f"docs/eval folders cited but missing: {missing}"


# --- commands -----------------------------------------------------------------------------------


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _commands(line: str) -> list[list[str]]:
    """The ``tidee`` invocations in a shell line, as argument lists without the program name."""
    try:
        tokens = shlex.split(line, comments=True)
    except ValueError:
        return []
    commands, current = [], []
    for tok in [*tokens, "&&"]:
        if tok in ("&&", "||", "&", ";", "|"):
            if current and Path(current[0]).name == "tidee":
                commands.append(current[1:])
            current = []
        else:
            current.append(tok)
    return commands


def readme_shell_commands() -> list[list[str]]:
    out = []
    for lang, code in fenced_blocks(README.read_text()):
        if lang in ("bash", "sh", "shell", ""):
            for line in code.splitlines():
                if line.lstrip().startswith((".venv/bin/tidee", "tidee ")):
                    out += _commands(line)
    return out


def test_readme_commands_parse() -> None:
    """Each command of the README's shell blocks parses as written, with exact flag names
    (argparse would also accept an abbreviation such as ``--mess`` for ``--mess-index``)."""
    commands = readme_shell_commands()
    assert any(c[:1] == ["server"] for c in commands), "README should show `tidee server`"
    parser = build_parser()
    for argv in commands:
        try:
            parser.parse_args(argv)
        except SystemExit as e:  # argparse reports the problem on stderr
            pytest.fail(f"README command does not parse: tidee {shlex.join(argv)} (exit {e.code})")
        assert not command_problems(argv), command_problems(argv)


def _flag_known(parser: argparse.ArgumentParser, token: str) -> bool:
    flag = token.split("=", 1)[0]
    return flag in parser._option_string_actions


def docs_inline_commands() -> list[tuple[str, list[str]]]:
    """``tidee ...`` code spans of the user docs that are whole commands (no placeholders)."""
    out = []
    for path in user_docs():
        for span in CODE_SPAN.findall(path.read_text()):
            if not span.startswith("tidee ") or re.search(r"\.\.\.|…|\[|\||<| / ", span):
                continue
            for argv in _commands(span):
                out.append((f"{path.relative_to(ROOT)}: `{span}`", argv))
    return out


def command_problems(argv: list[str]) -> list[str]:
    """What is wrong with a ``tidee`` argument list: an unknown subcommand, or a flag its
    subcommand does not have (exact names; values and required options are not checked)."""
    parser, rest = build_parser(), list(argv)
    while rest and (subs := _subparsers(parser)) and not rest[0].startswith("-"):
        if rest[0] not in subs:
            return [f"no subcommand {rest[0]!r}"]
        parser = subs[rest.pop(0)]
    return [f"unknown flag {t}" for t in rest if t.startswith("--") and not _flag_known(parser, t)]


def test_docs_commands_name_real_subcommands_and_flags() -> None:
    """Every inline ``tidee`` command of the docs names an existing subcommand and only its flags
    (a span may name just the command, so required options are not checked)."""
    problems = [f"{where}: {p}" for where, argv in docs_inline_commands() for p in command_problems(argv)]
    assert not problems, "\n".join(problems)


def test_command_check_refuses_abbreviations_and_unknown_subcommands() -> None:
    assert command_problems(["scene", "render", "--mess", "1"]) == ["unknown flag --mess"]
    assert command_problems(["eval", "nosuch"]) == ["no subcommand 'nosuch'"]
    assert command_problems(["scene", "render", "--mess-index", "1", "--out=x"]) == []
