"""The one rule every ``osa`` command follows for what it writes (docs/cli.md, "Outputs").

- An output file that exists is refused unless ``--force``; an output is never one
  of the command's inputs (not even with ``--force``).
- An output folder is created when missing; one that the same command wrote before
  (it holds the marker file ``.osa-output`` naming the command) is reused, its files
  replaced, and the command says so on stderr; any other non-empty folder needs
  ``--force``.
- Everything is checked before the work starts: a folder that cannot be created or
  written is refused then, not after an hour of simulation.

Problems are :class:`OutputRefusedError` with a one-line message (exit status 2).

JSON that a command prints or writes goes through :func:`json_text`: a non-finite
number (an error against an absurd truth, a sigma that overflowed) becomes ``null``
instead of a crash after the work is done.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

MARKER = ".osa-output"  # in an output folder: the name of the command that wrote it
# what the claims of the running command created: (the folders made, deepest first; the
# marker written where there was none), so that a refusal leaves nothing behind
_CLAIMED: list[tuple[list[Path], Path | None]] = []


def _finite(obj: object) -> object:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    return obj


def json_text(obj: object, *, indent: int | None = None) -> str:
    """``json.dumps`` that never fails on a non-finite float: NaN and infinities are
    written as ``null`` (JSON has neither)."""
    try:
        return json.dumps(obj, indent=indent, allow_nan=False)
    except ValueError:
        return json.dumps(_finite(obj), indent=indent, allow_nan=False)


class OutputRefusedError(ValueError):
    """An output that must not be written (one line, exit status 2)."""


def add_force_option(parser: argparse.ArgumentParser) -> None:
    """``--force``: replace existing outputs (never an input)."""
    parser.add_argument("--force", action="store_true",
                        help="replace existing output files (never one of the inputs)")


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def _check_not_input(path: Path, inputs: Iterable[str | os.PathLike]) -> None:
    for src in inputs:
        s = Path(src)
        if _same_file(path, s) or path.resolve() == s.resolve():
            raise OutputRefusedError(f"{path} is also an input: refusing to write over it")


def _check_writable_dir(folder: Path, what: Path) -> None:
    """Try it: a file created and removed (``os.access`` says yes to root on a
    read-only file system and to folders whose ACLs say no)."""
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".osa-write-check-")
    except OSError as exc:
        raise OutputRefusedError(f"cannot write {what}: {exc.strerror or exc}") from None
    os.close(fd)
    os.unlink(tmp)


def claim_output_file(path: str | os.PathLike, *, force: bool,
                      inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Check that ``path`` may be written now (see the module docstring); its parent
    folders are created. Returns it as a :class:`Path`."""
    p = Path(path)
    if str(path).endswith(("/", os.sep)):  # pathlib drops the slash: 'x/' would be file x
        raise OutputRefusedError(f"cannot write {path}: the name ends with '/', a folder's "
                                 "(give a file name)")
    _check_not_input(p, inputs)
    if p.is_dir():
        raise OutputRefusedError(f"cannot write {p}: is a directory")
    if p.exists() or p.is_symlink():
        if not force:
            raise OutputRefusedError(f"{p} exists (use --force to replace it)")
        if not os.access(p, os.W_OK):
            raise OutputRefusedError(f"cannot write {p}: permission denied")
    parent = p.parent if str(p.parent) else Path(".")
    blocker = next((a for a in (parent, *parent.parents) if a.exists()), None)
    if blocker is not None and not blocker.is_dir():
        raise OutputRefusedError(f"cannot write {p}: {blocker} is not a folder")
    made = [a for a in (parent, *parent.parents) if not a.exists()]
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputRefusedError(f"cannot write {p}: {exc.strerror or exc}") from None
    _CLAIMED.append((made, None))
    _check_writable_dir(parent, p)
    return p


def claim_output_dir(path: str | os.PathLike, *, command: str, force: bool,
                     inputs: Iterable[str | os.PathLike] = (),
                     quiet: bool = False) -> Path:
    """Check and create the output folder ``path`` of ``osa COMMAND`` (see the module
    docstring) and mark it as that command's. Returns it as a :class:`Path`."""
    p = Path(path)
    inputs = list(inputs)
    for src in inputs:
        s = Path(src).resolve()
        if s == p.resolve() or p.resolve() in s.parents:
            raise OutputRefusedError(f"{p} holds an input ({src}): choose another output folder")
    if p.exists() and not p.is_dir():
        raise OutputRefusedError(f"cannot write into {p}: it is a file, not a folder")
    marker = p / MARKER
    entries = []
    if p.is_dir():
        entries = [e for e in p.iterdir() if e.name != MARKER]
        owner = _marker_lines(p)[0] if marker.is_file() else None
        if entries and owner != command and not force:
            who = f"osa {owner}" if owner else "something else"
            raise OutputRefusedError(f"{p} is not empty and was written by {who} "
                                "(use --force to write into it)")
    blocker = next((a for a in (p, *p.parents) if a.exists()), None)
    if blocker is not None and not blocker.is_dir():
        raise OutputRefusedError(f"cannot create {p}: {blocker} is not a folder")
    made = [a for a in (p, *p.parents) if not a.exists()]
    new_marker = not marker.exists()
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputRefusedError(f"cannot create {p}: {exc.strerror or exc}") from None
    _CLAIMED.append((made, marker if new_marker else None))
    _check_writable_dir(p, p)
    try:
        marker.write_text(command + "\n")
    except OSError as exc:
        raise OutputRefusedError(f"cannot write into {p}: {exc.strerror or exc}") from None
    if entries and not quiet:  # said once the folder is known to be writable
        print(f"osa {command}: replacing the files in {p}", file=sys.stderr)
    return p


def _marker_lines(folder: Path) -> list[str]:
    """The marker's lines: the command's name, then the files it wrote (if listed)."""
    try:
        lines = (folder / MARKER).read_text(errors="replace").splitlines()
    except OSError:
        return [""]
    return [x.strip() for x in lines if x.strip()] or [""]


def files_written_before(path: str | os.PathLike, command: str) -> list[str]:
    """The files ``osa COMMAND`` listed in the marker of the folder ``path`` as its own
    (:func:`record_files`); none for a folder of another command, or no list."""
    lines = _marker_lines(Path(path))
    return lines[1:] if lines[0] == command else []


def record_files(folder: Path, command: str, names: Iterable[str]) -> None:
    """List ``names`` in the marker as the files ``osa COMMAND`` wrote into ``folder``:
    the next run into the folder removes those it does not write again."""
    with contextlib.suppress(OSError):
        (folder / MARKER).write_text("\n".join([command, *(Path(n).name for n in names)])
                                     + "\n")


def remove_stale(folder: Path, names: Iterable[str]) -> None:
    """Remove the files ``names`` that a command wrote into its own ``folder`` in an
    earlier run (:func:`files_written_before`) and does not write this time (a second
    agent's log, figures not drawn), so that the reused folder holds one run's files.
    Call it once every output is claimed (a refused command removes nothing)."""
    for name in names:
        old = folder / Path(name).name
        if old.is_file() or old.is_symlink():
            with contextlib.suppress(OSError):
                old.unlink()


def release_claims() -> None:
    """Undo what the claims of a refused command created (``osa`` calls it on exit
    status 2: refused before any work): the markers they added to folders that hold
    nothing else, and the folders they made, if still empty. Nothing else is touched."""
    while _CLAIMED:
        made, marker = _CLAIMED.pop()
        if marker is not None:
            with contextlib.suppress(OSError):
                if [e.name for e in marker.parent.iterdir()] == [MARKER]:
                    marker.unlink()
        for folder in made:  # deepest first; stops at the first that is not empty
            try:
                folder.rmdir()
            except OSError:
                break


def forget_claims() -> None:
    """The command ended: what its claims created is its output now."""
    _CLAIMED.clear()


@contextlib.contextmanager
def written_whole(path: str | os.PathLike) -> Iterator[Path]:
    """``with written_whole(out) as tmp: write(tmp)``: the file appears at ``out`` only
    once written in full (a temporary name in the same folder, then renamed), so an
    interrupted or failed write leaves the previous file, or nothing, never half a
    file. The temporary name ends with the real one (a ``.gz`` stays ``.gz``)."""
    p = Path(path)
    tmp = p.with_name(f".osa-tmp-{os.getpid()}-{p.name}")
    try:
        yield tmp
        os.replace(tmp, p)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()

