"""The docs: the site builds with --strict, every command line in them parses with the real parser,
every subcommand has an example, and the README stays short and free of run history."""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from stereopath.host.cli import build_parser

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
DOC_FILES = sorted([README, *(ROOT / "docs").glob("*.md")])
SHELL_LANGS = {"sh", "bash", "console", "shell"}
MAX_README_LINES = 150
# a numbered work period of the project's history ("session 12", "sessions 4 to 15"); a recorded
# scanning session is named by its id (20261128T154400Z-...), which this does not match
HISTORY = re.compile(r"\bsessions? \d{1,3}\b(?![-T:.\d])", re.IGNORECASE)


def shell_blocks(text: str) -> list[str]:
    """The contents of the fenced code blocks marked as shell (sh, bash, console, shell)."""
    blocks, lang, lines = [], None, []
    for line in text.splitlines():
        m = re.match(r"^\s*(```+|~~~+)\s*([\w+-]*)", line)
        if m and lang is None:
            lang, lines = m.group(2).lower() or "text", []
        elif m and lang is not None:
            if lang in SHELL_LANGS:
                blocks.append("\n".join(lines))
            lang = None
        elif lang is not None:
            lines.append(line)
    return blocks


def stereopath_lines(text: str) -> list[list[str]]:
    """Every ``stereopath ...`` invocation in the shell blocks of ``text``, as its argument list (after
    ``stereopath``); found at the start of a line or of a command joined with ``&&``, ``;`` or ``|``,
    also as ``sudo stereopath`` or ``.venv/bin/stereopath``."""
    found = []
    for block in shell_blocks(text):
        for line in block.splitlines():
            line = line.strip()
            if line.startswith("$ "):
                line = line[2:]
            if "stereopath" not in line:
                continue
            lex = shlex.shlex(line, posix=True, punctuation_chars=";&|")
            lex.whitespace_split = True
            lex.commenters = "#"
            words, command = list(lex), []
            for w in words + [";"]:
                if w and set(w) <= set(";&|"):
                    if command and command[0] == "sudo":
                        command = command[1:]
                    if command and Path(command[0]).name == "stereopath":
                        found.append(command[1:])
                    command = []
                else:
                    command.append(w)
    return found


def leaf_commands(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()) -> set[tuple[str, ...]]:
    """Every runnable subcommand of ``parser`` (a path of names: ``("device", "run")``)."""
    out: set[tuple[str, ...]] = set()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                inner = leaf_commands(sub, prefix + (name,))
                out |= inner or {prefix + (name,)}
    return out


def parse(argv: list[str]) -> tuple[argparse.Namespace | None, str]:
    """The namespace of ``stereopath ARGV`` (None when the parser refused it) and what it printed."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            return build_parser().parse_args(argv), ""
    except SystemExit:
        return None, err.getvalue().strip()


def command_of(ns: argparse.Namespace) -> tuple[str, ...]:
    group = ns.command
    sub = getattr(ns, f"{group}_command", None)
    return (group,) if sub is None else (group, sub)


def examples() -> list[tuple[str, list[str]]]:
    return [(p.relative_to(ROOT).as_posix(), argv) for p in DOC_FILES for argv in stereopath_lines(p.read_text())]


def test_shell_line_finder():
    text = ("```sh\nsudo .venv/bin/stereopath device install --dry-run   # what it would change\n"
            "pip install x && .venv/bin/stereopath demo --out 'a b'\nls stereopath\n```\n"
            "```toml\nstereopath = 1\n```\n```text\nstereopath sim --bogus\n```\n")
    assert stereopath_lines(text) == [["device", "install", "--dry-run"], ["demo", "--out", "a b"]]
    assert HISTORY.search("as measured in session 12") and HISTORY.search("Sessions 4 to 15")
    assert not HISTORY.search("session 20261128T154400Z-427e7a ended") and not HISTORY.search("a session 2-3 s")


def test_every_docs_command_line_parses():
    found = examples()
    assert len(found) >= 20, "the docs lost their command examples"
    bad = []
    for where, argv in found:
        ns, message = parse(argv)
        if ns is None:
            bad.append(f"{where}: stereopath {shlex.join(argv)}: {message.splitlines()[-1] if message else 'exit'}")
        elif not hasattr(ns, "_run"):
            bad.append(f"{where}: stereopath {shlex.join(argv)}: names a command group, not a command")
    assert not bad, "\n".join(bad)


def test_a_wrong_command_line_is_caught():
    assert parse(["device", "run", "--no-such-option"])[0] is None
    assert parse(["host", "reprocess", "s1"])[0] is None  # --out is required


def test_every_command_has_an_example():
    documented = set()
    for _, argv in examples():
        ns, _ = parse(argv)
        if ns is not None and hasattr(ns, "_run"):
            documented.add(command_of(ns))
    commands = leaf_commands(build_parser())
    assert ("device", "calibrate-stereo") in commands and ("demo",) in commands
    missing = sorted(" ".join(c) for c in commands - documented)
    assert not missing, f"commands without an example in the docs: {missing}"


def test_readme_is_short_and_has_no_run_history():
    lines = README.read_text().splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines (at most {MAX_README_LINES})"
    first_block = shell_blocks(README.read_text())[0].splitlines()
    assert "stereopath demo" in first_block[0] and "pytest" in first_block[1]
    assert "docs]" in first_block[1] or ",docs" in first_block[1]  # the suite builds the docs


def test_no_run_history_in_docs_or_code():
    files = DOC_FILES + sorted((ROOT / "device").rglob("*.py")) + sorted((ROOT / "host").rglob("*.py"))
    hits = [f"{p.relative_to(ROOT)}:{i}: {line.strip()}" for p in files
            for i, line in enumerate(p.read_text().splitlines(), 1) if HISTORY.search(line)]
    assert not hits, "numbered work periods (history belongs in CHANGELOG.md):\n" + "\n".join(hits)


def test_mkdocs_build_strict(tmp_path):
    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("material") is None:
        pytest.skip("mkdocs / mkdocs-material not installed (the docs extra)")
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict",
                          "-f", str(ROOT / "mkdocs.yml"), "-d", str(tmp_path / "site")],
                         capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert run.returncode == 0, run.stdout + run.stderr
    assert (tmp_path / "site" / "index.html").is_file()
    assert (tmp_path / "site" / "architecture" / "index.html").is_file()
