"""Android ``RangingResult`` fields as a CSV file (one ranging result a row).

The first line names the columns (any order, any case; extra columns are ignored):
``bssid``, ``status`` (``0`` or ``success`` is ``ok``; Android's codes 1 and 2 are
``fail`` and ``not_80211mc``; a word is kept), ``distance_mm``,
``distance_std_dev_mm``, ``rssi`` (dBm), ``num_attempted``, ``num_successful``, and a
time: ``utc_ms`` (Unix time of the result in ms) and/or ``elapsed_ns`` (the phone's
``elapsedRealtimeNanos``). A row with another number of cells than the header, or a
bad value, is counted and skipped. A UTF-8 byte order mark is dropped, and a line that
is not UTF-8 (Excel's plain "CSV" is saved in the Windows code page: an accented name in
an extra column) is read as Latin-1, the fields used being ASCII
(:func:`estimator.importers.common.text_lines`). The separator is the comma, or the
semicolon or tab of a spreadsheet's export when the header line holds no comma (numbers
keep the decimal point: a decimal comma is a ``bad_type``).
"""

from __future__ import annotations

import csv
from collections.abc import Iterator
from pathlib import Path

from estimator.importers.common import (
    RangesOptions,
    Skip,
    Source,
    SourceError,
    Stamped,
    Tally,
    integer,
    make_range,
    ms_to_ns,
    number,
    open_file,
    status_word,
    text_lines,
    time_integer,
)

FORMAT = "android-csv"
KIND = "ranges"
REQUIRED = ("bssid", "status")
TIMES = ("utc_ms", "elapsed_ns")


SEPARATORS = (",", ";", "\t")  # the comma; a spreadsheet's export in some locales


def separator(header: str) -> str:
    """The header line's separator: the comma, else the semicolon or tab it holds (a
    spreadsheet saves "CSV" with semicolons where the comma is the decimal mark)."""
    if "," in header:
        return ","
    return next((s for s in SEPARATORS[1:] if s in header), ",")


def _names(line: str) -> list[str]:
    return [c.strip().lower() for c in next(csv.reader([line], delimiter=separator(line)))]


def sniff(head: bytes) -> bool:
    """Whether the file's first line is a header naming ``bssid`` and ``distance_mm``."""
    for line in head.removeprefix(b"\xef\xbb\xbf").splitlines():
        if line.strip():
            try:
                names = _names(line.decode("utf-8", "replace"))
            except (csv.Error, StopIteration):
                return False
            return "bssid" in names and "distance_mm" in names
    return False


class Reader:
    """The ranging results of one CSV file (see the module docstring)."""

    def __init__(self, path: Path, options: RangesOptions) -> None:
        self.source = Source(path=path, format=FORMAT, kind=KIND, label="RangingResult rows",
                             utc_uncertainty_ns=500_000)  # utc_ms: 1 ms steps
        self.delimiter = ","
        self.columns = self._header()

    def _header(self) -> dict[str, int]:
        with open_file(self.source.path) as fh:
            for _, line in text_lines(fh, Tally().counts, eight_bit=True):
                self.delimiter = separator(line)
                try:
                    names = _names(line)
                except csv.Error:
                    break
                cols = {n: i for i, n in enumerate(names)}
                missing = [c for c in REQUIRED if c not in cols]
                if missing:
                    raise SourceError(f"{self.source.path}: the header names no "
                                      f"{' or '.join(missing)} column")
                if not any(t in cols for t in TIMES):
                    raise SourceError(f"{self.source.path}: the header names no time "
                                      "column (utc_ms or elapsed_ns)")
                return cols
        raise SourceError(f"{self.source.path}: no header line")

    def records(self, tally: Tally) -> Iterator[Stamped]:
        cols = self.columns
        n_cols = len(cols)
        with open_file(self.source.path) as fh:
            lines = text_lines(fh, tally.counts, eight_bit=True)
            next(lines, None)  # the header
            for _, line in lines:
                tally.counts.lines += 1
                try:
                    row = next(csv.reader([line], delimiter=self.delimiter))
                except csv.Error:
                    tally.skip("bad_csv")
                    continue
                if len(row) != n_cols:
                    tally.skip("wrong_column_count")
                    continue
                try:
                    yield self._result(row, cols)
                except Skip as s:
                    tally.skip(s.reason)

    @staticmethod
    def _result(row: list[str], cols: dict[str, int]) -> Stamped:
        def get(name: str) -> str | None:
            i = cols.get(name)
            return None if i is None else row[i]

        utc_ns = ms_to_ns(get("utc_ms"))
        elapsed = time_integer(get("elapsed_ns"))
        if utc_ns is None and elapsed is None:
            raise Skip("missing_field")
        if (utc_ns is not None and utc_ns < 0) or (elapsed is not None and elapsed < 0):
            raise Skip("negative_time")
        rec = make_range(
            bssid=get("bssid") or "",
            status=status_word(get("status") or ""),
            distance_mm=number(get("distance_mm")),
            std_dev_mm=number(get("distance_std_dev_mm")),
            rssi_dbm=number(get("rssi")),
            attempted=integer(get("num_attempted")),
            successful=integer(get("num_successful")),
        )
        return Stamped(rec, utc_ns=utc_ns, elapsed_ns=elapsed)

    def close(self) -> None:
        pass
