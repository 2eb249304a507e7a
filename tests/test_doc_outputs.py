"""Printed outputs in the README and docs/ are what the commands beside them print.

Every marked block (``<!-- output: small -->``, see ``tools/doc_outputs.py``) is run
in a fresh folder and its output compared with the document; ``slow`` blocks
(benchmarks) are only parsed here (their command must be in the block). Regenerate
with ``python tools/doc_outputs.py --write``.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("doc_outputs", ROOT / "tools" / "doc_outputs.py")
doc_outputs = importlib.util.module_from_spec(_spec)
sys.modules["doc_outputs"] = doc_outputs
_spec.loader.exec_module(doc_outputs)

SMALL = doc_outputs.all_blocks(("small",))


def test_the_documents_mark_their_small_outputs():
    names = {b.path.name for b in SMALL}
    # the default run's table, the example plans, the site example
    assert {"reproduce-paper.md", "planner.md", "cli.md", "README.md"} <= names
    for b in doc_outputs.all_blocks(("small", "slow")):
        assert b.commands, f"{b.name}: no command beside the output"
        assert b.output, f"{b.name}: no output"


@pytest.mark.parametrize("block", SMALL, ids=lambda b: b.name)
def test_the_document_shows_what_the_command_prints(block):
    diff = doc_outputs.check(block)
    assert diff is None, (f"{block.name} no longer matches its command "
                          f"(python tools/doc_outputs.py --write):\n{diff}")


def _doc(tmp_path: Path, shown: str, options: str = "", name: str = "doc.md") -> Path:
    path = tmp_path / name
    path.write_text(f"intro\n\n<!-- output: small{options} -->\n```sh\necho 'took 12 ms'\n"
                    f"printf 'a\\nb\\n'\n```\nprints\n```text\n{shown}\n```\n<!-- /output -->\n")
    return path


def test_the_checker_sees_a_changed_figure(tmp_path, monkeypatch):
    monkeypatch.setattr(doc_outputs, "ROOT", tmp_path)
    for name in doc_outputs.LINKED:
        (tmp_path / name).mkdir()
    good = doc_outputs.blocks(_doc(tmp_path, "took 12 ms\na\nb"))[0]
    assert good.commands == ["echo 'took 12 ms'", "printf 'a\\nb\\n'"]
    assert doc_outputs.check(good) is None
    stale = doc_outputs.blocks(_doc(tmp_path, "took 12 ms\na\nc", name="stale.md"))[0]
    assert "-c" in doc_outputs.check(stale) and "+b" in doc_outputs.check(stale)
    masked = doc_outputs.blocks(_doc(tmp_path, "took 99 ms\na\nb", "; mask: [0-9]+ ms"))[0]
    assert doc_outputs.check(masked) is None
    # the mask is the text after "mask:", without the spaces around it
    tight = doc_outputs.blocks(_doc(tmp_path, "took 99 ms\na\nb", "; mask: k [0-9]+ ",
                                    name="tight.md"))[0]
    assert tight.masks[0].pattern == "k [0-9]+"
    assert doc_outputs.check(tight) is None
    kept = doc_outputs.blocks(_doc(tmp_path, "a", "; keep: ^a"))[0]
    assert doc_outputs.check(kept) is None
    assert doc_outputs.write(stale) is True
    assert "took 12 ms\na\nb\n```\n<!-- /output -->" in (tmp_path / "stale.md").read_text()
    assert doc_outputs.check(doc_outputs.blocks(tmp_path / "stale.md")[0]) is None


def test_a_console_block_runs_each_prompt(tmp_path, monkeypatch):
    monkeypatch.setattr(doc_outputs, "ROOT", tmp_path)
    for name in doc_outputs.LINKED:
        (tmp_path / name).mkdir()
    path = tmp_path / "c.md"
    path.write_text("<!-- output: small -->\n```console\n$ echo one\none\n$ echo two\nTWO\n```\n"
                    "<!-- /output -->\n")
    block = doc_outputs.blocks(path)[0]
    assert "+two" in doc_outputs.check(block)


def test_a_malformed_marker_is_named(tmp_path, monkeypatch):
    monkeypatch.setattr(doc_outputs, "ROOT", tmp_path)
    path = tmp_path / "bad.md"
    path.write_text("<!-- output: small -->\n```sh\necho x\n```\n```text\nx\n```\n")
    with pytest.raises(doc_outputs.DocFormatError, match=r"bad\.md:1"):
        doc_outputs.blocks(path)
