"""The generated results file: each command's printed report in a section of its own.

`meshfg accuracy --results FILE` and `meshfg bench --results FILE` (FILE: docs/results.md in
this repository) write the text they print into FILE, between markers named after the section,
under the command line that made it, the machine (CPU model, cores) and the commit it ran on.
A run rewrites its own section only: the other commands' sections are kept as they are. The bench
writes a section per CPU model (`bench_section`): its figures depend on the machine, and the
project's machines differ, so a run on one keeps the figures of the others. Figures are
therefore never typed by hand, and each says what made it and where.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

__all__ = ["HEADER", "bench_section", "commit", "read_section", "section_text", "write_section"]

HEADER = """# Results

Generated: each section is written by the command it names (`--results docs/results.md`), with
the machine and the commit it ran on; running a command again rewrites its section only (the
bench's: the one of its CPU model). Do not edit by hand. What the columns mean and which
targets they are judged against: README.md, "Results".
"""

_REPOSITORY = Path(__file__).resolve().parent.parent


def _begin(section: str) -> str:
    return f"<!-- meshfg results: {section}: begin -->"


def _end(section: str) -> str:
    return f"<!-- meshfg results: {section}: end -->"


def bench_section(machine: str) -> str:
    """The name of `meshfg bench`'s section for the CPU `machine` (as blas.cpu_model names it):
    one section per CPU model (module doc)."""
    return f"bench on {machine}"


def commit(repository: Path = _REPOSITORY, results: Path | None = None) -> str:
    """The checkout's commit (12 hex digits), marked when tracked files other than the results
    file `results` differ from it (the file the commands write is their output, not the code
    they ran); a one-line reason where there is no git checkout."""
    def git(*arguments: str) -> str:
        return subprocess.run(["git", "-C", str(repository), *arguments], capture_output=True, text=True,
                              check=True, timeout=30).stdout.strip()

    root = Path(repository).resolve()
    inside = results is not None and Path(results).resolve().is_relative_to(root)
    excluded = [f":(exclude){Path(results).resolve().relative_to(root)}"] if inside else []
    try:
        head = git("rev-parse", "--short=12", "HEAD")
        changed = git("status", "--porcelain", "--untracked-files=no", "--", ".", *excluded)
    except (OSError, subprocess.SubprocessError):
        return "unknown (not a git checkout)"
    return f"{head} with uncommitted changes" if changed else head


def section_text(section: str, command_line: str, report: str, machine: str, commit_: str,
                 markdown: bool) -> str:
    """A section: heading, what made it, and `report` exactly as the command printed it (in a
    text block unless it is markdown)."""
    body = report.rstrip("\n") if markdown else f"```text\n{report.rstrip(chr(10))}\n```"
    return (f"{_begin(section)}\n## {section}\n\n`{command_line}` on {machine}, commit {commit_}.\n\n"
            f"{body}\n{_end(section)}\n")


def write_section(path: Path, section: str, command_line: str, report: str, *, markdown: bool,
                  machine: str | None = None, commit_: str | None = None) -> None:
    """Put `report` into `path`'s section `section` (replacing that section, keeping the others;
    the file is created with its header if missing). machine and commit_ default to this
    process's CPU (blas.cpu_model) and this checkout's commit."""
    if machine is None:
        from meshfg_ros.blas import cpu_model

        machine = cpu_model()
    block = section_text(section, command_line, report, machine, commit(results=path) if commit_ is None else commit_,
                         markdown)
    text = path.read_text() if path.exists() else HEADER
    begin, end = _begin(section), _end(section)
    start = text.find(begin)
    stop = text.find(end, start) if start >= 0 else -1
    if start >= 0 and stop >= 0:
        stop += len(end)
        if text[stop:stop + 1] == "\n":
            stop += 1
        text = text[:start] + block + text[stop:]
    else:
        text = text.rstrip("\n") + "\n\n" + block
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    partial.write_text(text)
    os.replace(partial, path)


def read_section(path: Path, section: str) -> str | None:
    """The text between a section's markers (heading included), or None where it has none."""
    text = path.read_text()
    start = text.find(_begin(section))
    stop = text.find(_end(section), start) if start >= 0 else -1
    return None if start < 0 or stop < 0 else text[start + len(_begin(section)):stop]
