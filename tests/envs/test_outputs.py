"""The one output rule of every command (envs/commands/_outputs.py)."""

from __future__ import annotations

import os

import pytest

from envs.commands._outputs import MARKER, OutputRefusedError, claim_output_dir, claim_output_file


def test_existing_file_needs_force_and_an_input_is_never_an_output(tmp_path):
    f = tmp_path / "a.jsonl"
    f.write_text("keep\n")
    with pytest.raises(OutputRefusedError, match=r"exists .*--force"):
        claim_output_file(f, force=False)
    assert f.read_text() == "keep\n"
    assert claim_output_file(f, force=True) == f
    with pytest.raises(OutputRefusedError, match="also an input"):
        claim_output_file(f, force=True, inputs=[f])
    with pytest.raises(OutputRefusedError, match="also an input"):  # another spelling of it
        claim_output_file(tmp_path / "." / "a.jsonl", force=True, inputs=[str(f)])
    new = claim_output_file(tmp_path / "x" / "y" / "b.jsonl", force=False)
    assert new.parent.is_dir() and not new.exists()


def test_file_under_a_file_or_a_directory_is_refused(tmp_path):
    (tmp_path / "f").write_text("")
    with pytest.raises(OutputRefusedError, match="not a folder"):
        claim_output_file(tmp_path / "f" / "out.csv", force=True)
    with pytest.raises(OutputRefusedError, match="is a directory"):
        claim_output_file(tmp_path, force=True)


def test_output_folder_reused_only_by_the_command_that_wrote_it(tmp_path, capsys):
    d = tmp_path / "out"
    claim_output_dir(d, command="run", force=False)
    assert (d / MARKER).read_text() == "run\n"
    (d / "report.json").write_text("{}")
    claim_output_dir(d, command="run", force=False)  # the same command: reused, said
    assert "replacing the files" in capsys.readouterr().err
    with pytest.raises(OutputRefusedError, match="written by osa run"):
        claim_output_dir(d, command="search", force=False)
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("precious")
    with pytest.raises(OutputRefusedError, match="something else"):
        claim_output_dir(other, command="run", force=False)
    claim_output_dir(other, command="run", force=True)
    assert (other / "notes.txt").read_text() == "precious"
    with pytest.raises(OutputRefusedError, match="holds an input"):
        claim_output_dir(tmp_path, command="run", force=True, inputs=[other / "notes.txt"])


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes anywhere")
def test_unwritable_folder_is_refused_before_work(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(OutputRefusedError, match="permission denied"):
            claim_output_file(ro / "x.csv", force=False)
    finally:
        ro.chmod(0o700)
