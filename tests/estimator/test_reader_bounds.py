"""The reader is bounded on any input and reads a log once (docs/log-format.md,
"Limits"); duplicates and clock jumps are handled and counted ("Suspicious data").

Memory is measured for real: ``osa replay`` runs in a subprocess under
``RLIMIT_AS`` (an address-space limit far below what an unbounded reader needs for
these inputs) and must answer with one line.
"""

from __future__ import annotations

import gzip
import io
import json
import math
import os
import resource
import signal
import subprocess
import sys
import threading
import time
import tracemalloc
import warnings
from pathlib import Path

import pytest

import estimator.logio as logio
from envs.cli import main as osa_main
from estimator.logio import (
    MAX_LINE_BYTES,
    LogStream,
    NotALogError,
    iter_log_sorted,
    printable,
    read_log,
)
from estimator.replay import ReplayOptions, replay_logs

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "example_flight.jsonl"
HEADER = '{"type":"header","format":"osa-log","version":1,"agent":"uav-1"}'
GNSS = ('{"type":"gnss","t_ns":%d,"lat":36.715123,"lon":-4.478321,"alt_m":152.31,'
        '"acc_m":0.92}')
RTT = ('{"type":"rtt","t_ns":%d,"bssid":"a4:77:33:0f:1e:02","status":"ok",'
       '"range_m":74.3,"rssi_dbm":-71}')
# an address-space limit: the interpreter with NumPy and SciPy loaded fits in ~250 MiB
# (one BLAS thread); an unbounded reader needs GBs for the inputs below
RLIMIT_AS_BYTES = 512 << 20


def _lines(path: Path, lines: list[str | bytes]) -> Path:
    path.write_bytes(b"".join((x if isinstance(x, bytes) else x.encode()) + b"\n"
                             for x in lines))
    return path


def _run_limited(*args: str, stdin: bytes | None = None,
                 env: dict | None = None) -> subprocess.CompletedProcess:
    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (RLIMIT_AS_BYTES, RLIMIT_AS_BYTES))

    return subprocess.run(
        [sys.executable, "-m", "envs.cli", *args], cwd=ROOT, capture_output=True,
        input=stdin, preexec_fn=limit, timeout=120,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
             "PYTHONPATH": str(ROOT), **(env or {})})


def _one_line(stderr: bytes) -> str:
    text = stderr.decode()
    assert text.count("\n") == 1 and "Traceback" not in text, text[-2000:]
    return text


# ------------------------------------------------------------------------ line cap


def test_a_line_beyond_the_cap_is_skipped_counted_and_never_held(tmp_path: Path) -> None:
    path = tmp_path / "long.jsonl"
    with path.open("wb") as fh:
        fh.write((HEADER + "\n" + GNSS % 1000 + "\n").encode())
        fh.write(b'{"type":"gnss","pad":"' + b"x" * (40 << 20) + b'"}\n')  # 40 MiB
        fh.write((RTT % 3000 + "\n").encode())
        fh.write(b"y" * (MAX_LINE_BYTES + 1))  # the last line, cut, without a newline
    tracemalloc.start()
    try:
        log = read_log(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert [r.t_ns for r in log.gnss] == [1000] and [r.t_ns for r in log.rtt] == [3000]
    assert log.counts.rejected == {"line_too_long": 2}
    assert peak < 8 * MAX_LINE_BYTES, f"peak {peak / 1e6:.1f} MB"  # not the 40 MiB line


def test_a_line_of_exactly_the_cap_is_read(tmp_path: Path) -> None:
    pad = MAX_LINE_BYTES - len(RTT % 3000) - len(',"note":""')
    line = (RTT % 3000)[:-1] + ',"note":"' + "n" * pad + '"}'
    assert len(line) == MAX_LINE_BYTES
    log = read_log(_lines(tmp_path / "edge.jsonl", [HEADER, line]))
    assert len(log.rtt) == 1 and log.counts.unknown_fields == 1 and not log.counts.rejected


# ------------------------------------------------------------------------ not a log


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="no /dev/zero")
def test_dev_zero_is_not_a_log_and_stays_small() -> None:
    with pytest.raises(NotALogError, match="no valid record in its first 16 MiB"):
        read_log("/dev/zero")
    proc = _run_limited("replay", "/dev/zero")
    assert proc.returncode == 2
    assert _one_line(proc.stderr) == (
        "osa replay: /dev/zero: not a flight log (no valid record in its first 16 MiB)\n")


def _gzip_bomb(path: Path, mib: int) -> Path:
    """A valid header, then one line of ``mib`` MiB of 'x' in ~1 kB gzip members."""
    member = gzip.compress(b"x" * (1 << 20), compresslevel=9, mtime=0)
    path.write_bytes(gzip.compress((HEADER + "\n").encode(), mtime=0) + member * mib
                     + gzip.compress(b"\n", mtime=0))
    return path


def test_a_gzip_bomb_is_refused_in_one_line_within_the_memory_limit(tmp_path: Path) -> None:
    bomb = _gzip_bomb(tmp_path / "bomb.jsonl.gz", 400)  # 0.4 MB that expands to 400 MiB
    assert bomb.stat().st_size < 1 << 20
    with pytest.raises(logio.LogError, match="expands more than 200 times"):
        read_log(bomb)
    proc = _run_limited("replay", str(bomb))
    assert proc.returncode == 2
    line = _one_line(proc.stderr)
    assert line.startswith(f"osa replay: {bomb}: refused: its gzip stream expands more than "
                           "200 times")


def test_a_well_compressed_log_is_not_a_bomb(tmp_path: Path, monkeypatch) -> None:
    """Near-identical records (failed requests a millisecond apart) compress far less
    than 200 times: checked from the first MiB on, the log reads whole."""
    monkeypatch.setattr(logio, "GZIP_RATIO_FLOOR_BYTES", 1 << 20)
    path = tmp_path / "repetitive.jsonl.gz"
    fail = '{{"type":"rtt","t_ns":{},"bssid":"a4:77:33:0f:1e:02","status":"fail"}}\n'
    text = HEADER + "\n" + "".join(fail.format(i * 1_000_000) for i in range(60_000))
    path.write_bytes(gzip.compress(text.encode(), compresslevel=9))
    assert len(text) / path.stat().st_size < logio.GZIP_MAX_RATIO / 4
    assert sum(1 for _ in iter_log_sorted(path)) == 60_000


# ------------------------------------------------------------------------ one pass


def _json_replay(paths, **kw) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return replay_logs(paths, ReplayOptions(**kw)).to_json()


def test_standard_input_is_read_once_and_loses_nothing(monkeypatch, capsys) -> None:
    data = EXAMPLE.read_bytes()
    expected = _json_replay([EXAMPLE])
    stdin = io.TextIOWrapper(io.BufferedReader(io.BytesIO(data)))
    monkeypatch.setattr(sys, "stdin", stdin)
    assert osa_main(["replay", "-", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == expected
    assert not stdin.closed  # the command never closes standard input


def test_standard_input_as_a_real_pipe() -> None:
    expected = _json_replay([EXAMPLE])
    proc = _run_limited("replay", "-", "--json", stdin=EXAMPLE.read_bytes())
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout) == expected


def test_a_fifo_is_read_once(tmp_path: Path) -> None:
    fifo = tmp_path / "log.fifo"
    os.mkfifo(fifo)
    data = EXAMPLE.read_bytes()

    def write() -> None:
        with fifo.open("wb") as fh:  # blocks until the reader opens it: once
            fh.write(data)

    writer = threading.Thread(target=write, daemon=True)
    writer.start()
    got = _json_replay([fifo])
    writer.join(timeout=30)
    assert not writer.is_alive()
    expected = _json_replay([EXAMPLE])
    assert got["estimates"] == expected["estimates"]
    assert got["association"] == expected["association"]


def test_the_same_pipe_given_twice_is_refused(capsys) -> None:
    assert osa_main(["replay", "-", "-"]) == 2
    assert capsys.readouterr().err == ("osa replay: standard input: given twice (a log fused "
                                       "with itself counts every range twice)\n")


# ------------------------------------------------------------------------ spill files


def test_sigterm_during_a_long_replay_removes_the_spill_files(tmp_path: Path) -> None:
    """A replay reads a fifo past the in-memory sort (200 000 records: one spilled run),
    then waits for more; SIGTERM then stops it with status 143, one line, and no
    ``osa-sort-*`` folder left (without the handler it dies with the folder there)."""
    spill = tmp_path / "tmp"
    spill.mkdir()
    fifo = tmp_path / "log.fifo"
    os.mkfifo(fifo)
    proc = subprocess.Popen(
        [sys.executable, "-m", "envs.cli", "replay", str(fifo)], cwd=ROOT,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        env={**os.environ, "TMPDIR": str(spill), "PYTHONPATH": str(ROOT)})
    fh = fifo.open("wb")
    try:
        fh.write((HEADER + "\n").encode())
        fail = '{{"type":"rtt","t_ns":{},"bssid":"a4:77:33:0f:1e:02","status":"fail"}}\n'
        chunk = "".join(fail.format(t) for t in range(210_000))
        fh.write(chunk.encode())
        fh.flush()
        deadline = time.monotonic() + 120
        while not list(spill.glob("osa-sort-*/run0.pkl")):
            assert proc.poll() is None and time.monotonic() < deadline, "no spill run"
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)  # the writer keeps the fifo open: it is reading
        _, err = proc.communicate(timeout=60)
    finally:
        fh.close()
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143
    assert _one_line(err) == "osa replay: terminated\n"
    assert list(spill.iterdir()) == []


# ------------------------------------------------------------------------ limits


def test_responders_beyond_the_cap_are_counted(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(logio, "MAX_BSSIDS", 3)
    lines = [HEADER]
    for i in range(5):
        b = f"a4:77:33:0f:1e:{i:02x}"
        lines.append(RTT.replace("a4:77:33:0f:1e:02", b) % (1000 + i))
        lines.append(RTT.replace("a4:77:33:0f:1e:02", b) % (2000 + i))
    log = read_log(_lines(tmp_path / "many.jsonl", lines))
    assert sorted({r.bssid for r in log.rtt}) == [f"a4:77:33:0f:1e:0{i}" for i in range(3)]
    assert log.counts.rejected == {"too_many_bssids": 4}


def test_unknown_record_types_are_counted_under_a_bounded_number_of_names(
        tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(logio, "MAX_UNKNOWN_TYPES", 2)
    lines = [HEADER, GNSS % 1] + [f'{{"type":"kind{i}"}}' for i in (1, 2, 3, 4, 1)]
    log = read_log(_lines(tmp_path / "u.jsonl", lines))
    assert log.counts.unknown_types == {"kind1": 2, "kind2": 1, "(others)": 2}


def test_truth_is_kept_once_per_responder(tmp_path: Path) -> None:
    truth = ('{"type":"truth","bssid":"a4:77:33:0f:1e:02","lat":36.7,"lon":-4.4,'
             '"alt_m":%s}')
    log = read_log(_lines(tmp_path / "t.jsonl", [HEADER, truth % 100, truth % 200, RTT % 1]))
    assert [t.alt_m for t in log.truth] == [100.0]
    assert log.counts.rejected == {"duplicate_truth": 1}


@pytest.mark.parametrize(("config", "agl", "offset"), [
    ('{"agl_m":5e-324,"range_offset_m":0.5}', None, 0.5),
    ('{"agl_m":-45}', None, None),
    ('{"agl_m":1e30}', None, None),
    ('{"agl_m":0}', None, None),
    ('{"agl_m":40,"range_offset_m":-1e9}', 40.0, None),
])
def test_absurd_header_settings_are_dropped_and_said(tmp_path: Path, config, agl,
                                                     offset) -> None:
    header = HEADER[:-1] + ',"config":' + config + "}"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        log = read_log(_lines(tmp_path / "h.jsonl", [header, RTT % 1]))
    assert (log.header.agl_m, log.header.range_offset_m) == (agl, offset)
    assert log.header.agent == "uav-1"  # the rest of the header is used
    assert log.counts.rejected == {"bad_config": 1}
    assert any("ignored (the default applies)" in str(w.message) for w in caught)


def test_control_characters_in_log_strings_are_escaped(tmp_path: Path) -> None:
    header = HEADER.replace('"uav-1"', '"uav\\u001b[2J\\u202e"')
    fail = ('{"type":"rtt","t_ns":5,"bssid":"a4:77:33:0f:1e:02","status":"no\\u0007pe",'
            '"range_m":1.0}')
    log = read_log(_lines(tmp_path / "esc.jsonl",
                          [header, fail, '{"type":"im\\u001bu","t_ns":1}']))
    assert log.header.agent == "uav\\x1b[2J\\u202e"
    assert log.rtt[0].status == "no\\x07pe"
    assert list(log.counts.unknown_types) == ["im\\x1bu"]
    assert printable("plain ascii, ünïcode") == "plain ascii, ünïcode"


# ------------------------------------------------------------------------ suspicious data


def _example_lines() -> list[str]:
    return EXAMPLE.read_text().splitlines()


def _shift(lines: list[str], start: int, shift_ns: int) -> list[str]:
    out = []
    for i, line in enumerate(lines):
        obj = json.loads(line)
        if i >= start and "t_ns" in obj:
            obj["t_ns"] += shift_ns
        out.append(json.dumps(obj))
    return out


def _estimates(report: dict) -> list[dict]:
    return [{k: v for k, v in e.items() if k != "flags"} for e in report["estimates"]]


@pytest.fixture(scope="module")
def original() -> dict:
    return _json_replay([EXAMPLE], modes=("baseline", "refined"))


@pytest.mark.parametrize("how", ["log-twice", "every-line-twice"])
def test_duplicated_records_give_the_original_estimates(tmp_path: Path, original,
                                                        how: str) -> None:
    lines = _example_lines()
    dup = lines + lines if how == "log-twice" else [x for line in lines for x in (line, line)]
    report = _json_replay([_lines(tmp_path / "dup.jsonl", dup)], modes=("baseline", "refined"))
    assert _estimates(report) == _estimates(original)  # 1.44 m, not 5.12 m
    n_timed = sum('"t_ns"' in line for line in lines)
    assert report["association"]["duplicates"] == n_timed
    assert report["association"]["clock_jumps"] == 0
    assert report["flags"] == ["duplicate_records"]
    assert all(e["flags"] == ["duplicate_records"] for e in report["estimates"])
    assert report["rejected_lines"] == {"duplicate_header": 1, "duplicate_truth": 1}
    assert original["flags"] == [] and "flags" not in original["estimates"][0]


@pytest.mark.parametrize(("jump_s", "within_m"), [(-300.0, 0.05), (-2000.0, 0.05),
                                                  (1000.0, 0.05)])
def test_a_clock_jump_splits_the_log_and_is_counted(tmp_path: Path, original, jump_s: float,
                                                    within_m: float) -> None:
    """Half-way through the example flight the phone clock jumps: back by 300 s (the two
    halves would interleave: 4.71 m instead of 1.44 m), back before the first record,
    or forward. The estimate stays within ``within_m`` of the original's."""
    lines = _example_lines()
    jumped = _shift(lines, len(lines) // 2, int(jump_s * 1e9))
    report = _json_replay([_lines(tmp_path / "jump.jsonl", jumped)],
                          modes=("baseline", "refined"))
    assert report["association"]["clock_jumps"] == 1
    assert report["flags"] == ["clock_jump"]
    for got, want in zip(report["estimates"], original["estimates"], strict=True):
        assert got["status"] == want["status"] and got["flags"] == ["clock_jump"]
        north = (got["lat"] - want["lat"]) * 111_320.0
        east = (got["lon"] - want["lon"]) * 111_320.0 * math.cos(math.radians(want["lat"]))
        assert math.hypot(north, east) < within_m, (got, want)
        assert abs(got["err_h_m"] - want["err_h_m"]) < within_m


def test_the_stream_after_a_backward_jump_is_retimed_after_the_one_before(tmp_path) -> None:
    lines = [HEADER] + [GNSS % (t * 10**9) for t in (100, 101, 102, 5, 6)]
    st = LogStream(path="x")
    times = [r.t_ns for r in iter_log_sorted(_lines(tmp_path / "j.jsonl", lines), st)]
    gap = int(logio.CLOCK_JUMP_GAP_S * 1e9)
    assert times == [100 * 10**9, 101 * 10**9, 102 * 10**9, 102 * 10**9 + gap,
                     103 * 10**9 + gap]
    assert st.counts.clock_jumps_back == 1
    # late lines (less than CLOCK_JUMP_BACK_S out of order) are no jump
    lines = [HEADER] + [GNSS % (t * 10**9) for t in (100, 101, 95, 102)]
    st = LogStream(path="y")
    times = [r.t_ns // 10**9 for r in iter_log_sorted(_lines(tmp_path / "k.jsonl", lines), st)]
    assert times == [95, 100, 101, 102] and st.counts.clock_jumps_back == 0


def _rtt_to(bssid: str, t_ns: int) -> str:
    return RTT.replace("a4:77:33:0f:1e:02", bssid) % t_ns


def test_a_stream_per_responder_after_another_is_no_jump(tmp_path) -> None:
    """Fixes and the ranges to one responder in time order, then every range to a
    second responder (a converter writing one topic after another): sorted, no jump."""
    ms = 10**6
    first = [x for k in range(1000) for x in (GNSS % (k * 100 * ms),
                                             _rtt_to("a4:77:33:0f:1e:02", k * 100 * ms + 5))]
    second = [_rtt_to("a4:77:33:0f:1e:03", k * 100 * ms + 7) for k in range(1000)]
    st = LogStream(path="x")
    times = [r.t_ns for r in iter_log_sorted(_lines(tmp_path / "s.jsonl",
                                                    [HEADER, *first, *second]), st)]
    assert st.counts.clock_jumps_back == 0
    assert len(times) == 3000 and times == sorted(times) and times[-1] == 99_900 * ms + 7


@pytest.mark.parametrize("how", ["reboot", "reversed"])
def test_a_reboot_at_a_high_rate_is_a_jump_and_reversed_lines_are_not(tmp_path,
                                                                      how) -> None:
    """100 records a second (fixes and ranges to two responders) for 60 s. With the
    clock reset to 5 s at 40 s (a reboot): one jump, the 2000 records after it re-timed
    after the 4000 before. Without a reset, the 6000 lines reversed: sorted by t_ns, no
    jump (before, every record 10 s older than the first was re-timed after it)."""
    ms = 10**6
    lines = []
    for k in range(6000):
        t = (k * 10 if k < 4000 or how == "reversed" else 5000 + (k - 4000) * 10) * ms
        lines.append([GNSS % t, _rtt_to("a4:77:33:0f:1e:02", t),
                      _rtt_to("a4:77:33:0f:1e:03", t)][k % 3])
    if how == "reversed":
        lines = lines[::-1]
    st = LogStream(path="x")
    times = [r.t_ns for r in iter_log_sorted(_lines(tmp_path / "r.jsonl", [HEADER, *lines]),
                                             st)]
    assert times == sorted(times) and len(times) == 6000
    if how == "reboot":  # the new stretch starts CLOCK_JUMP_GAP_S after the old one's end
        assert st.counts.clock_jumps_back == 1
        gap = int(logio.CLOCK_JUMP_GAP_S * 1e9)
        assert times[4000] == 39_990 * ms + gap and times[3999] == 39_990 * ms
    else:
        assert st.counts.clock_jumps_back == 0
        assert times == [k * 10 * ms for k in range(6000)]
