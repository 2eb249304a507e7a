"""docs/log-format.md agrees with the reader: its example log reads clean, every
field the reader knows and every reason it skips a line is documented."""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from estimator import logio
from estimator.logio import read_log
from estimator.replay import ReplayOptions, replay_logs

DOC = Path(__file__).resolve().parents[2] / "docs" / "log-format.md"


def _blocks(kind: str) -> list[str]:
    return re.findall(rf"```{kind}\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S)


@pytest.fixture
def example(tmp_path) -> Path:
    (body,) = _blocks("jsonl")
    path = tmp_path / "tiny.jsonl"
    path.write_text(body, encoding="utf-8")
    return path


def test_the_complete_example_reads_clean(example):
    log = read_log(example)
    assert log.counts.rejected == {} and not log.counts.unknown_types
    assert log.counts.unknown_fields == 0
    assert log.header.agent == "uav-1" and log.header.agl_m == 45.0
    assert len(log.gnss) == 3 and len(log.rtt) == 3 and len(log.truth) == 1
    assert [g.t_ns for g in log.gnss] == sorted(g.t_ns for g in log.gnss)  # reordered
    lines = example.read_text().splitlines()
    assert json.loads(lines[5])["t_ns"] > json.loads(lines[6])["t_ns"]  # out of order in file


def test_the_example_replays_as_the_doc_says(example):
    rep = replay_logs([example], ReplayOptions())
    assert rep.get("a4:77:33:0f:1e:02", "baseline").status == "bootstrapping"
    assert sum(rep.association.associated.values()) == 2
    assert sum(rep.association.interpolated.values()) == 2
    assert sum(rep.association.rtt.values()) == 3


def test_the_record_examples_are_valid_records(tmp_path):
    objs = [json.loads(b) for b in _blocks("json")]
    assert sorted(o["type"] for o in objs) == ["gnss", "header", "rtt", "truth"]
    path = tmp_path / "records.jsonl"
    path.write_text("\n".join(json.dumps(o) for o in objs) + "\n")
    log = read_log(path)
    assert log.counts.rejected == {} and log.counts.unknown_fields == 0
    assert (len(log.gnss), len(log.rtt), len(log.truth)) == (1, 1, 1)


def test_every_known_field_is_documented():
    text = DOC.read_text(encoding="utf-8")
    for kind, fields in logio._KNOWN_FIELDS.items():
        assert f"`{kind}`" in text
        for name in fields - {"type", "config"}:
            assert f"`{name}`" in text, f"{kind}.{name}"
    for name in ("config.agl_m", "config.range_offset_m"):
        assert f"`{name}`" in text


def test_every_skip_reason_is_documented():
    source = Path(logio.__file__).read_text(encoding="utf-8")
    reasons = set(re.findall(r'_Reject\("(\w+)"\)', source))
    reasons |= set(re.findall(r'reject\("(\w+)"\)', source))
    reasons |= set(re.findall(r'"missing_field" if kind is None else "(\w+)"', source))
    assert {"not_json", "not_utf8", "bad_bssid", "duplicate_header"} <= reasons
    text = DOC.read_text(encoding="utf-8")
    missing = sorted(r for r in reasons if f"`{r}`" not in text)
    assert not missing, f"docs/log-format.md does not explain {missing}"


def test_the_python_snippet_writes_a_readable_log(tmp_path, monkeypatch):
    (snippet,) = _blocks("python")
    monkeypatch.chdir(tmp_path)
    exec(compile(snippet, str(DOC), "exec"), {})  # run the documented example
    log = read_log(tmp_path / "flight.jsonl.gz")
    assert log.counts.rejected == {} and len(log.gnss) == 1 and len(log.rtt) == 1


def _reordered(how: str) -> list[str]:
    """examples/example_flight.jsonl's lines in another order a writer may use."""
    lines = (Path(__file__).resolve().parents[2] / "examples" / "example_flight.jsonl"
             ).read_text(encoding="utf-8").splitlines()
    head = [ln for ln in lines if '"type":"header"' in ln or '"type":"truth"' in ln]
    gnss = [ln for ln in lines if '"type":"gnss"' in ln]
    rtt = [ln for ln in lines if '"type":"rtt"' in ln]
    assert len(head) == 2 and len(gnss) > 2000 and len(rtt) == 960
    if how == "fixes-then-ranges":
        return head + gnss + rtt
    if how == "ranges-then-fixes":
        return head + rtt + gnss
    if how == "reversed":
        return head + (gnss + rtt)[::-1]
    order = np.random.default_rng(7).permutation(len(gnss) + len(rtt))
    timed = gnss + rtt
    return head + [timed[i] for i in order]


@pytest.mark.parametrize("how", ["fixes-then-ranges", "ranges-then-fixes", "reversed",
                                 "shuffled"])
def test_any_order_of_the_lines_gives_the_time_ordered_logs_estimates(tmp_path, how):
    """The contract: lines are not guaranteed to be in time order, readers order by
    t_ns. A file written one stream after the other, reversed or shuffled is the same
    log: no clock jump, every range associated as in the file in time order (before,
    every fix then every range was read as a backward clock jump: 0 of 960 associated,
    status no_data)."""
    opts = ReplayOptions(modes=("baseline",))
    want = replay_logs([Path(__file__).resolve().parents[2] / "examples"
                        / "example_flight.jsonl"], opts).to_json()
    path = tmp_path / f"{how}.jsonl"
    path.write_text("\n".join(_reordered(how)) + "\n", encoding="utf-8")
    with warnings.catch_warnings():
        warnings.simplefilter("error", logio.LogWarning)
        got = replay_logs([path], opts).to_json()
    assert got["flags"] == [] and got["association"]["clock_jumps"] == 0
    assert got["association"]["associated"] == want["association"]["associated"] > 900
    assert got["estimates"] == want["estimates"]
    text = " ".join(DOC.read_text(encoding="utf-8").split())
    assert "order does not matter" in text and "one stream after the other" in text
