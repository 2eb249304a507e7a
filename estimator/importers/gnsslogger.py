"""Google GnssLogger text files: their ``Fix`` lines.

GnssLogger writes comma-separated records, one a line, each starting with its type
(``Raw``, ``Status``, ``Fix``, ``OrientationDeg``...); ``#`` lines are comments, and
the comment ``# Fix,Provider,LatitudeDegrees,...`` names the ``Fix`` columns (read from
the file, so any column order works; the app's v3 order is assumed without it). Used:
``LatitudeDegrees``, ``LongitudeDegrees``, ``AltitudeMeters`` (Android's
``Location.getAltitude()``: already above the WGS84 ellipsoid), ``AccuracyMeters``,
``VerticalAccuracyMeters``, ``UnixTimeMillis`` (UTC) and ``elapsedRealtimeNanos`` (the
phone's clock). Older files name them ``Latitude``, ``Longitude``, ``Altitude``,
``Accuracy`` and ``(UTC)TimeInMs``; both are read. An empty or ``NaN`` accuracy is
unknown. Only fixes of one provider are used: ``GPS`` unless ``--topic`` names another
(``FLP``, ``NLP``); the others are counted.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from estimator.importers.common import (
    GnssOptions,
    Skip,
    Source,
    Stamped,
    Tally,
    accuracy_field,
    make_fix,
    number,
    open_file,
    text_lines,
    time_integer,
)

FORMAT = "gnsslogger"
KIND = "gnss"
DEFAULT_COLUMNS = (
    "Fix", "Provider", "LatitudeDegrees", "LongitudeDegrees", "AltitudeMeters", "SpeedMps",
    "AccuracyMeters", "BearingDegrees", "UnixTimeMillis", "SpeedAccuracyMps",
    "BearingAccuracyDegrees", "elapsedRealtimeNanos", "VerticalAccuracyMeters",
)
ALIASES = {  # GnssLogger v1/v2 column names
    "Latitude": "LatitudeDegrees",
    "Longitude": "LongitudeDegrees",
    "Altitude": "AltitudeMeters",
    "Accuracy": "AccuracyMeters",
    "(UTC)TimeInMs": "UnixTimeMillis",
}


def sniff(head: bytes) -> bool:
    """Whether the start of a file looks like a GnssLogger log (a ``Fix`` line or its
    column comment)."""
    for line in head.splitlines()[:400]:
        s = line.lstrip(b"# ").rstrip()
        if s.startswith(b"Fix,") and (b"Latitude" in s or line.startswith(b"Fix,")):
            return True
    return False


class Reader:
    """The fixes of one GnssLogger file (see the module docstring)."""

    def __init__(self, path: Path, options: GnssOptions) -> None:
        self.options = options
        self.provider = (options.topic or "GPS").upper()
        self.source = Source(path=path, format=FORMAT, kind=KIND,
                             label=f"Fix lines of provider {self.provider}",
                             utc_uncertainty_ns=500_000)  # UnixTimeMillis: 1 ms steps
        open_file(path).close()

    def records(self, tally: Tally) -> Iterator[Stamped]:
        columns = {name: i for i, name in enumerate(DEFAULT_COLUMNS)}
        with open_file(self.source.path) as fh:
            for _, line in text_lines(fh, tally.counts):
                if line.startswith("#"):
                    body = line.lstrip("# ").strip()
                    if body.startswith("Fix,"):
                        names = [ALIASES.get(c.strip(), c.strip()) for c in body.split(",")]
                        columns = {name: i for i, name in enumerate(names)}
                    continue
                kind = line.split(",", 1)[0].strip()
                if kind != "Fix":
                    tally.counts.unknown_types[kind[:40] or "(empty)"] += 1
                    continue
                tally.counts.lines += 1
                fields = line.split(",")
                provider = fields[columns["Provider"]].strip().upper() if (
                    "Provider" in columns and columns["Provider"] < len(fields)) else ""
                if provider != self.provider:
                    tally.counts.unknown_types[f"Fix {provider or '(no provider)'}"] += 1
                    continue
                try:
                    yield self._fix(fields, columns, tally)
                except Skip as s:
                    tally.skip(s.reason)

    def _fix(self, fields: list[str], columns: dict[str, int], tally: Tally) -> Stamped:
        def get(name: str) -> str | None:
            i = columns.get(name)
            return fields[i] if i is not None and i < len(fields) else None

        utc_ms = time_integer(get("UnixTimeMillis"))
        elapsed = time_integer(get("elapsedRealtimeNanos"))
        if utc_ms is None and elapsed is None:
            raise Skip("missing_field")
        if (utc_ms is not None and utc_ms < 0) or (elapsed is not None and elapsed < 0):
            raise Skip("negative_time")
        fix = make_fix(
            lat_deg=number(get("LatitudeDegrees")),
            lon_deg=number(get("LongitudeDegrees")),
            alt_m=number(get("AltitudeMeters")),
            acc_m=accuracy_field(get("AccuracyMeters")),
            vacc_m=accuracy_field(get("VerticalAccuracyMeters")),
            default_acc_m=self.options.default_acc_m,
        )
        tally.heights["ellipsoid"] += 1
        return Stamped(fix, utc_ns=None if utc_ms is None else utc_ms * 1_000_000,
                       elapsed_ns=elapsed)

    def close(self) -> None:
        pass
