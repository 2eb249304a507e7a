"""Printed outputs in the README and docs/, regenerated from the commands beside them.

A figure a reader sees in the docs is the output of a command shown next to it. Each
such pair sits between two HTML comments (invisible on GitHub)::

    <!-- output: small; mask: [0-9]+ ms -->
    ```sh
    osa plan optimal -o opt.plan ...
    ```
    ```text
    osa plan optimal -> opt.plan
      ...
    ```
    <!-- /output -->

or as one ``console`` block whose ``$ `` lines are the commands and whose other lines
are what they print. The first word after ``output:`` is the block's size: ``small``
blocks (seconds to run) are regenerated and compared by the test suite
(``tests/test_doc_outputs.py``), ``slow`` ones (benchmarks of minutes) only here with
``--all``. Options, separated by ``;``:

* ``mask: REGEX``: what a match covers (a timing, say) is not compared; the docs keep
  the value of the last regeneration.
* ``keep: REGEX``: only the printed lines matching it are compared and shown.
* ``stderr``: compare what the command writes on stderr too (after stdout).

The commands run with ``bash -e`` in an empty temporary folder holding links to the
repository's ``examples``, ``sim``, ``benchmarks``, ``docs`` and ``tests``, with this
interpreter's ``osa`` first on ``PATH``. Usage::

    python tools/doc_outputs.py            # check the small blocks (exit 1 on a mismatch)
    python tools/doc_outputs.py --write    # regenerate the small blocks in place
    python tools/doc_outputs.py --write --all   # ... and the slow ones (minutes)
"""

from __future__ import annotations

import argparse
import difflib
import os
import re
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = ("README.md", "docs/*.md")
LINKED = ("examples", "sim", "benchmarks", "docs", "tests")
OPEN = re.compile(r"^<!-- output: *(small|slow) *((?:;[^>]*)?)-->\s*$")
CLOSE = re.compile(r"^<!-- /output -->\s*$")
FENCE = re.compile(r"^```(\w*)\s*$")
MASKED = "\u2026"
BOUNDARY = "@@osa-doc-output-boundary@@"


class DocFormatError(ValueError):
    """A marked block that is not a command block followed by an output block."""


@dataclass
class Block:
    """One marked command-and-output pair of a document."""

    path: Path
    line: int  # 1-based line of the opening marker
    size: str  # "small" | "slow"
    commands: list[str]
    output: list[str]  # the lines shown in the document (a console's: with its prompts)
    output_span: tuple[int, int]  # 0-based [start, end) of the output lines in the file
    console: bool = False
    masks: list[re.Pattern] = field(default_factory=list)
    keep: re.Pattern | None = None
    stderr: bool = False

    @property
    def name(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"

    def script(self) -> str:
        return "\n".join(self.commands) + "\n"

    def kept(self, lines: list[str]) -> list[str]:
        """The lines a document shows of printed ones: right-stripped, ``keep`` applied
        (a console's ``$`` prompts always kept), trailing blank lines dropped."""
        out = [ln.rstrip() for ln in lines]
        if self.keep is not None:
            out = [ln for ln in out if ln.startswith("$ ") or self.keep.search(ln)]
        while out and not out[-1]:
            out.pop()
        return out

    def comparable(self, lines: list[str]) -> list[str]:
        """``lines`` as compared: :meth:`kept`, with the masked parts replaced."""
        out = self.kept(lines)
        for mask in self.masks:
            out = [mask.sub(MASKED, ln) for ln in out]
        return out


def _options(text: str) -> list[tuple[str, str]]:
    """A marker's ``key: value`` options in order (``mask`` may come several times)."""
    pairs = []
    for part in text.split(";"):
        if part.strip():
            key, _, value = part.partition(":")
            pairs.append((key.strip(), value.strip()))
    return pairs


def _fenced(lines: list[str], i: int, where: str, prose: bool = False
            ) -> tuple[str, int, int]:
    """The fenced block starting at or after line ``i`` (after blank lines, and after a
    few words such as "prints" when ``prose``): (language, first, end) lines."""
    while i < len(lines) and (not lines[i].strip()
                              or (prose and not lines[i].startswith("```"))):
        if prose and CLOSE.match(lines[i]):
            break
        i += 1
    m = FENCE.match(lines[i]) if i < len(lines) else None
    if m is None:
        raise DocFormatError(f"{where}: expected a fenced block")
    j = i + 1
    while j < len(lines) and not lines[j].startswith("```"):
        j += 1
    if j == len(lines):
        raise DocFormatError(f"{where}: unclosed fenced block")
    return m.group(1), i + 1, j


def _commands(body: list[str]) -> list[str]:
    return [ln for ln in body if ln.strip() and not ln.lstrip().startswith("#")]


def blocks(path: Path) -> list[Block]:
    """Every marked block of one document."""
    lines = path.read_text(encoding="utf-8").splitlines()
    found: list[Block] = []
    i = 0
    while i < len(lines):
        m = OPEN.match(lines[i])
        if m is None:
            i += 1
            continue
        where = f"{path.relative_to(ROOT)}:{i + 1}"
        opts = _options(m.group(2))
        keep = [v for k, v in opts if k == "keep"]
        lang, a, b = _fenced(lines, i + 1, where)
        common = dict(path=path, line=i + 1, size=m.group(1),
                      masks=[re.compile(v) for k, v in opts if k == "mask"],
                      keep=re.compile(keep[-1]) if keep else None,
                      stderr=any(k == "stderr" for k, _ in opts))
        if lang == "console":
            cmds = [ln[2:] for ln in lines[a:b] if ln.startswith("$ ")]
            found.append(Block(commands=cmds, output=lines[a:b], output_span=(a, b),
                               console=True, **common))
            end = b + 1
        else:
            cmds = _commands(lines[a:b])
            _, c, d = _fenced(lines, b + 1, where, prose=True)
            found.append(Block(commands=cmds, output=lines[c:d], output_span=(c, d), **common))
            end = d + 1
        while end < len(lines) and not lines[end].strip():
            end += 1
        if end >= len(lines) or not CLOSE.match(lines[end]):
            raise DocFormatError(f"{where}: no <!-- /output --> right after the output block")
        i = end + 1
    return found


def documents() -> list[Path]:
    out: list[Path] = []
    for pattern in DOCUMENTS:
        out += sorted(ROOT.glob(pattern))
    return out


def all_blocks(sizes: tuple[str, ...] = ("small",)) -> list[Block]:
    return [b for p in documents() for b in blocks(p) if b.size in sizes]


def _environment() -> dict[str, str]:
    env = dict(os.environ)
    bindir = str(Path(sys.executable).parent)
    env["PATH"] = bindir + os.pathsep + env.get("PATH", "")
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env["MPLBACKEND"] = "Agg"
    env.setdefault("PYTHONHASHSEED", "0")
    return env


def run(block: Block, timeout_s: float = 1800.0) -> list[str]:
    """What the block's commands print, run in a fresh folder (see the module doc)."""
    with tempfile.TemporaryDirectory(prefix="osa-doc-") as tmp:
        for name in LINKED:
            os.symlink(ROOT / name, Path(tmp) / name)
        scripts = ([c + "\n" for c in block.commands] if block.console
                   else [block.script()])
        shell = "set -e\n"
        for script in scripts:
            shell += script
            if block.console:
                shell += f"echo '{BOUNDARY}'\n"
        proc = subprocess.run(["bash", "-c", shell], cwd=tmp, env=_environment(),
                              capture_output=True, text=True, timeout=timeout_s)
        if proc.returncode != 0:
            raise RuntimeError(f"{block.name}: the commands failed (exit {proc.returncode}):"
                               f"\n{proc.stderr.strip()[-2000:]}")
        text = proc.stdout + (proc.stderr if block.stderr else "")
        if block.console:
            return _console(block, text)
        return block.kept(text.splitlines())


def _console(block: Block, text: str) -> list[str]:
    """A console block's lines: each ``$ command`` followed by what it printed."""
    parts = text.split(BOUNDARY + "\n")
    out: list[str] = []
    for cmd, printed in zip(block.commands, parts, strict=False):
        out += [f"$ {cmd}", *block.kept(printed.splitlines())]
    return out


def check(block: Block) -> str | None:
    """None when the document shows what the commands print, else a unified diff."""
    want = block.comparable(block.output)
    got = block.comparable(run(block))
    if want == got:
        return None
    return "\n".join(difflib.unified_diff(want, got, "document", "commands", lineterm=""))


def write(block: Block) -> bool:
    """Replace the block's output in its document; True when it changed."""
    got = run(block)
    lines = block.path.read_text(encoding="utf-8").splitlines()
    a, b = block.output_span
    if block.comparable(lines[a:b]) == block.comparable(got):
        return False  # only masked parts differ: keep the document as it is
    lines[a:b] = got
    block.path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return True


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--write", action="store_true", help="regenerate the outputs in place")
    ap.add_argument("--all", action="store_true", help="the slow blocks too")
    ap.add_argument("--only", default="", help="only blocks whose name contains this")
    args = ap.parse_args(argv)
    sizes = ("small", "slow") if args.all else ("small",)
    bad = 0
    # documents change under --write: re-read the blocks of a document after each write
    for path in documents():
        k = 0
        while True:
            todo = [b for b in blocks(path) if b.size in sizes and args.only in b.name]
            if k >= len(todo):
                break
            block = todo[k]
            k += 1
            print(f"{block.name} ({block.size}) ...", file=sys.stderr, flush=True)
            if args.write:
                if write(block):
                    print(f"  rewrote {block.name}", file=sys.stderr)
            else:
                diff = check(block)
                if diff:
                    bad += 1
                    print(diff)
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
