#!/usr/bin/env python3
"""Checks the documentation: README.md and docs/*.md.

1. Links: every relative markdown link or image (`[text](path#anchor)`, `![alt](path)`, and
   reference definitions `[label]: path`) must point at a file or folder of the repository, and
   an `#anchor` at a heading of the target markdown file (GitHub's slugs: lowercase, punctuation
   other than hyphens and underscores dropped, spaces to hyphens, `-1`, `-2` ... for repeats).
   http(s) and mailto links are not fetched. Links inside code blocks and code spans are skipped.

2. With --run: every fenced code block whose info string is `sh runnable` is run. Each
   non-empty line that is not a comment is one command, run with `bash -e -o pipefail -c` from
   the repository root, with a `gprflow` symlink to the binary under test first on PATH, in the
   order the lines appear; README.md first, then docs/*.md in sorted order. The run stops at the
   first command that fails (non-zero exit or timeout) and reports its file, line, command, exit
   status and the tail of its output. Commands should write only under out/ (created here).

Usage:
  tools/scripts/check-docs.py                       # links only
  tools/scripts/check-docs.py --list                # the runnable commands, file:line: command
  tools/scripts/check-docs.py --run [--gprflow target/debug/gprflow] [--timeout 120]

Exit status: 0 when everything passed, 1 on a broken link or a failed command, 2 on bad usage
(a missing binary). Python 3.11, standard library only.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
import urllib.parse
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RUNNABLE_INFO = ["sh", "runnable"]
TAIL_LINES = 40

FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,})(.*)$")
ATX_HEADING = re.compile(r"^ {0,3}(#{1,6})(?:[ \t]+(.*?))?(?:[ \t]+#+)?[ \t]*$")
SETEXT_UNDERLINE = re.compile(r"^ {0,3}(=+|-+)[ \t]*$")
HTML_ANCHOR = re.compile(r"""<a\s+[^>]*(?:name|id)\s*=\s*["']([^"']+)["']""", re.IGNORECASE)
INLINE_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*(<[^>]*>|[^()\s]*(?:\([^()\s]*\)[^()\s]*)*)(?:\s+(?:\"[^\"]*\"|'[^']*'))?\s*\)")
REFERENCE_DEF = re.compile(r"^ {0,3}\[[^\]]+\]:\s*(<[^>]*>|\S+)")
SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")


@dataclass
class Line:
    """A line of a markdown file with what the parser found out about it."""

    number: int
    text: str
    in_code: bool


@dataclass
class Command:
    """One runnable command."""

    file: Path
    line: int
    text: str


def relative(path: Path) -> str:
    try:
        return str(path.relative_to(ROOT))
    except ValueError:
        return str(path)


def doc_files() -> list[Path]:
    """README.md first, then docs/*.md in sorted order."""
    files = [ROOT / "README.md"]
    files += sorted((ROOT / "docs").glob("*.md"))
    return [f for f in files if f.is_file()]


def scan(path: Path) -> tuple[list[Line], list[tuple[int, str, list[str]]], list[str]]:
    """The file's lines (marked in or out of fenced code), its fenced blocks as
    (line of the opening fence, info string, [(line number, text)...]) and problems."""
    lines: list[Line] = []
    blocks = []
    problems: list[str] = []
    fence: tuple[str, int] | None = None  # (fence characters, length)
    block = None
    for number, text in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        match = FENCE.match(text)
        if fence is None:
            if match and not (match.group(1)[0] == "`" and "`" in match.group(2)):
                fence = (match.group(1)[0], len(match.group(1)))
                block = (number, match.group(2).strip(), [])
                lines.append(Line(number, text, True))
                continue
            lines.append(Line(number, text, False))
        else:
            closing = match and match.group(1)[0] == fence[0] and len(match.group(1)) >= fence[1]
            if closing and not match.group(2).strip():
                blocks.append(block)
                fence, block = None, None
            else:
                block[2].append((number, text))
            lines.append(Line(number, text, True))
    if fence is not None:
        problems.append(f"{relative(path)}:{block[0]}: code block never closed")
        blocks.append(block)
    return lines, blocks, problems


CODE_SPAN = re.compile(r"(?<!`)(`+)(?!`)(.+?)(?<!`)\1(?!`)")


def strip_code_spans(text: str) -> str:
    """The line with its inline code spans blanked out (so links in them are not links)."""
    return CODE_SPAN.sub(lambda m: " " * len(m.group(0)), text)


def heading_text(raw: str) -> str:
    """What GitHub renders of a heading's markdown, roughly: links as their text, no code
    backticks, no emphasis stars, no HTML tags."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", raw)
    text = re.sub(r"<[^>]+>", "", text)
    return text.replace("`", "").replace("*", "")


def slug(text: str) -> str:
    """GitHub's anchor of a heading: lowercase, everything but letters, digits, underscores,
    hyphens and spaces dropped, spaces to hyphens."""
    text = heading_text(text).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path, cache: dict[Path, set[str]]) -> set[str]:
    """Every anchor a markdown file defines: heading slugs (repeats numbered) and HTML ids."""
    if path in cache:
        return cache[path]
    lines, _, _ = scan(path)
    found: set[str] = set()
    seen: dict[str, int] = {}

    def add(title: str) -> None:
        base = slug(title)
        n = seen.get(base, 0)
        seen[base] = n + 1
        found.add(base if n == 0 else f"{base}-{n}")

    previous: Line | None = None
    for line in lines:
        if not line.in_code:
            match = ATX_HEADING.match(line.text)
            if match:
                add(match.group(2) or "")
            elif (
                SETEXT_UNDERLINE.match(line.text)
                and previous is not None
                and not previous.in_code
                and previous.text.strip()
                and not ATX_HEADING.match(previous.text)
                and not previous.text.lstrip().startswith(("-", "*", "+", "|", ">"))
            ):
                add(previous.text.strip())
            for name in HTML_ANCHOR.findall(line.text):
                found.add(name)
        previous = line
    cache[path] = found
    return found


def link_targets(lines: list[Line]) -> list[tuple[int, str]]:
    """(line number, target) of every link and image outside code."""
    targets = []
    for line in lines:
        if line.in_code:
            continue
        text = strip_code_spans(line.text)
        for match in INLINE_LINK.finditer(text):
            targets.append((line.number, match.group(1)))
        match = REFERENCE_DEF.match(text)
        if match:
            targets.append((line.number, match.group(1)))
    return targets


def check_links(files: list[Path]) -> list[str]:
    """Every broken link of these files, as `file:line: why`."""
    problems: list[str] = []
    cache: dict[Path, set[str]] = {}
    for path in files:
        lines, blocks, scan_problems = scan(path)
        problems += scan_problems
        for start, info, _ in blocks:
            words = info.split()
            if "runnable" in words and words != RUNNABLE_INFO:
                problems.append(
                    f"{relative(path)}:{start}: code block marked {info!r}: a runnable block's info string is 'sh runnable'"
                )
        for number, target in link_targets(lines):
            where = f"{relative(path)}:{number}"
            target = target[1:-1] if target.startswith("<") and target.endswith(">") else target
            if not target:
                problems.append(f"{where}: empty link")
                continue
            if SCHEME.match(target):
                continue  # http(s), mailto: not fetched
            file_part, _, anchor = target.partition("#")
            file_part = urllib.parse.unquote(file_part)
            anchor = urllib.parse.unquote(anchor)
            if file_part:
                if file_part.startswith("/"):
                    resolved = (ROOT / file_part.lstrip("/")).resolve()
                else:
                    resolved = (path.parent / file_part).resolve()
                if ROOT not in resolved.parents and resolved != ROOT:
                    problems.append(f"{where}: {target}: points outside the repository")
                    continue
                if not resolved.exists():
                    problems.append(f"{where}: {target}: no such file ({relative(resolved)})")
                    continue
            else:
                resolved = path
            if anchor and resolved.is_file() and resolved.suffix.lower() == ".md":
                if anchor not in anchors(resolved, cache):
                    problems.append(f"{where}: {target}: no heading with anchor #{anchor} in {relative(resolved)}")
    return problems


def runnable_commands(files: list[Path]) -> list[Command]:
    commands = []
    for path in files:
        _, blocks, _ = scan(path)
        for _, info, body in blocks:
            if info.split() != RUNNABLE_INFO:
                continue
            for number, text in body:
                stripped = text.strip()
                if stripped and not stripped.startswith("#"):
                    commands.append(Command(path, number, stripped))
    return commands


def tail(path: Path, n: int) -> str:
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    return "\n".join(lines[-n:])


def kill_group(pgid: int) -> None:
    """Ends what is left of a command's process group (background jobs it started)."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(pgid, sig)
        except ProcessLookupError:
            return
        time.sleep(0.2)


def run_commands(commands: list[Command], gprflow: Path, timeout_s: float) -> bool:
    """Runs the commands in order; stops at the first failure. True when all passed."""
    (ROOT / "out").mkdir(exist_ok=True)
    started = time.monotonic()
    per_file: dict[Path, float] = {}
    timings: list[tuple[float, Command]] = []
    with tempfile.TemporaryDirectory(prefix="check-docs-") as tmp:
        bindir = Path(tmp) / "bin"
        bindir.mkdir()
        (bindir / "gprflow").symlink_to(gprflow)
        env = dict(os.environ)
        env["PATH"] = f"{bindir}{os.pathsep}{env.get('PATH', '')}"
        log = Path(tmp) / "output.txt"
        for index, command in enumerate(commands, start=1):
            where = f"{relative(command.file)}:{command.line}"
            print(f"[{index}/{len(commands)}] {where}: {command.text}", flush=True)
            t0 = time.monotonic()
            with open(log, "wb") as out:
                process = subprocess.Popen(
                    ["bash", "-e", "-o", "pipefail", "-c", command.text],
                    cwd=ROOT,
                    env=env,
                    stdin=subprocess.DEVNULL,
                    stdout=out,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,
                )
                try:
                    status: int | str = process.wait(timeout=timeout_s)
                except subprocess.TimeoutExpired:
                    status = f"timed out after {timeout_s:g} s"
                kill_group(process.pid)
                process.wait()
            seconds = time.monotonic() - t0
            per_file[command.file] = per_file.get(command.file, 0.0) + seconds
            timings.append((seconds, command))
            if status != 0:
                what = status if isinstance(status, str) else f"exit status {status} after {seconds:.1f} s"
                print(f"\nFAILED {where}: {what}", file=sys.stderr)
                print(f"  command: {command.text}", file=sys.stderr)
                print(f"  last {TAIL_LINES} lines of its output:", file=sys.stderr)
                for line in tail(log, TAIL_LINES).splitlines():
                    print(f"  | {line}", file=sys.stderr)
                print(f"{index - 1} of {len(commands)} commands passed before it", file=sys.stderr)
                return False
            print(f"    ok ({seconds:.1f} s)", flush=True)
    total = time.monotonic() - started
    print(f"\n{len(commands)} runnable commands passed in {total:.1f} s")
    for path, seconds in per_file.items():
        print(f"  {relative(path):<28} {seconds:7.1f} s")
    print("  slowest:")
    for seconds, command in sorted(timings, key=lambda t: -t[0])[:5]:
        print(f"  {seconds:7.1f} s  {relative(command.file)}:{command.line}: {command.text}")
    return True


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", action="store_true", help="also run the `sh runnable` blocks")
    parser.add_argument("--list", action="store_true", help="print the runnable commands and exit")
    default_binary = Path(os.environ.get("CARGO_TARGET_DIR", "target")) / "debug" / "gprflow"
    parser.add_argument(
        "--gprflow",
        type=Path,
        default=default_binary,
        help="the gprflow binary the commands run (default: $CARGO_TARGET_DIR or target, /debug/gprflow)",
    )
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds per command (default 120)")
    args = parser.parse_args()

    files = doc_files()
    commands = runnable_commands(files)
    if args.list:
        for command in commands:
            print(f"{relative(command.file)}:{command.line}: {command.text}")
        return 0

    problems = check_links(files)
    for problem in problems:
        print(problem, file=sys.stderr)
    print(f"links: {len(files)} files checked, {len(problems)} problem(s)")

    ok = not problems
    if args.run:
        binary = args.gprflow if args.gprflow.is_absolute() else ROOT / args.gprflow
        if not (binary.is_file() and os.access(binary, os.X_OK)):
            print(f"check-docs: no gprflow binary at {binary} (build it, or pass --gprflow)", file=sys.stderr)
            return 2
        ok = run_commands(commands, binary.resolve(), args.timeout) and ok
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
