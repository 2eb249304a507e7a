"""PX4 ULog files (``.ulg``), read with pyulog: the GNSS receiver's topic.

The topic is ``vehicle_gps_position`` (it wins when both are logged) or
``sensor_gps``, instance (``multi_id``) 0; ``--topic NAME`` or ``--topic NAME[ID]``
names another. pyulog loads only that topic, so memory grows with the GNSS topic,
not with the file. Fields, as the file's own format declares them:

- latitude/longitude: ``lat``/``lon`` as integers in 1e-7 degrees (PX4 up to v1.13)
  or ``latitude_deg``/``longitude_deg`` in degrees (v1.14 on);
- height: ``alt_ellipsoid`` (integer mm) or ``altitude_ellipsoid_m``; when the file
  has none (or a zero one beside a non-zero MSL height), ``alt`` / ``altitude_msl_m``
  above mean sea level plus ``--geoid-offset``, with a warning;
- ``eph``, ``epv`` (m): ``acc_m``, ``vacc_m``; ``fix_type`` (0-1 no fix and 8
  extrapolated are skipped as ``no_fix``; 2 ``2d``, 3 ``3d``, 4 ``dgps``, 5
  ``rtk_float``, 6 ``rtk_fixed``); ``satellites_used``;
- ``time_utc_usec``: UTC; fixes before the receiver had UTC (0) are skipped as
  ``no_utc``.

The GNSS streams not read (another ``multi_id``, the other topic) are counted as
other records (``vehicle_gps_position[1]``), as a DataFlash log's other receiver is.

pyulog skips corrupt parts of a file itself (it resumes at the next sync message) and
does not say how much it skipped: ``corrupt_data`` counts the GNSS messages lost,
estimated from the gaps in the topic's timestamps (at least 1 for a corrupt file). A
file that ends in the middle of one of the topic's messages (a recording cut off) has
it counted as ``truncated``.
"""

from __future__ import annotations

import contextlib
import io
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from estimator.importers.common import (
    GnssOptions,
    Skip,
    Source,
    SourceError,
    Stamped,
    Tally,
    brief,
    ellipsoidal_m,
    float32_decimal,
    make_fix,
    open_file,
)

FORMAT = "ulog"
KIND = "gnss"
MAGIC = b"ULog\x01\x12\x35"
TOPICS = ("vehicle_gps_position", "sensor_gps")  # in order of preference
FIX_TYPES = {2: "2d", 3: "3d", 4: "dgps", 5: "rtk_float", 6: "rtk_fixed", 7: None}
_TOPIC = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)(?:\[(\d+)\])?$")


def sniff(head: bytes) -> bool:
    return head.startswith(MAGIC)


def parse_topic(text: str) -> tuple[str, int | None]:
    """``NAME`` or ``NAME[ID]`` -> (name, instance or None)."""
    m = _TOPIC.match(text.strip())
    if not m:
        raise ValueError(f"--topic {text!r} is not NAME or NAME[ID]")
    return m.group(1), (int(m.group(2)) if m.group(2) is not None else None)


class _Lines(io.TextIOBase):
    """A text sink that keeps nothing but the number of lines written (pyulog prints
    its warnings)."""

    def __init__(self) -> None:
        self.n = 0

    def write(self, s: str) -> int:
        self.n += s.count("\n")
        return len(s)


class _EndWatch:
    """The file as pyulog reads it, remembering its last two reads: pyulog stops without
    a word where the file ends in the middle of a message (a recording cut off), and
    these say which message that was."""

    def __init__(self, path: Path) -> None:
        self._fh = open_file(path)
        self.seek, self.tell, self.close = self._fh.seek, self._fh.tell, self._fh.close
        self.before: tuple[int, bytes] = (0, b"")
        self.last: tuple[int, bytes] = (0, b"")

    def read(self, n: int = -1) -> bytes:
        data = self._fh.read(n)
        self.before, self.last = self.last, (n, data)
        return data

    def cut_data_id(self) -> int | None:
        """The message id of the data (``D``) message the file ends in, when pyulog's
        last reads were its 3-byte header and a payload short of the size it gives
        (with the id's two bytes in it)."""
        (n0, head), (n1, body) = self.before, self.last
        if n0 != 3 or len(head) != 3 or head[2] != ord("D"):
            return None
        if n1 != int.from_bytes(head[:2], "little") or not 2 <= len(body) < n1:
            return None
        return int.from_bytes(body[:2], "little")


class Reader:
    """The fixes of one ULog file's GNSS topic (see the module docstring)."""

    def __init__(self, path: Path, options: GnssOptions) -> None:
        from pyulog import ULog
        from pyulog.exceptions import ULogException

        self.options = options
        self.source = Source(path=path, format=FORMAT, kind=KIND,
                             utc_uncertainty_ns=500)  # time_utc_usec: 1 us steps
        try:
            want, instance = parse_topic(options.topic) if options.topic else (None, None)
        except ValueError as exc:
            raise SourceError(f"{path}: {exc}") from None
        names = [want] if want else list(TOPICS)
        sink = _Lines()
        fh = _EndWatch(path)
        try:
            with contextlib.redirect_stdout(sink):
                ulog = ULog(fh, message_name_filter_list=names)
        except (ULogException, OSError, ValueError, KeyError, IndexError) as exc:
            raise SourceError(f"{path}: not a readable ULog file ({brief(exc)})") from None
        finally:
            fh.close()
        self.corrupt = bool(ulog.file_corruption)
        data = {(d.name, d.multi_id): d for d in ulog.data_list}
        name = want or next((t for t in TOPICS if any(k[0] == t for k in data)), None)
        if name is None:
            raise SourceError(f"{path}: no {' or '.join(names)} topic with data")
        ids = sorted(k[1] for k in data if k[0] == name)
        if not ids:
            raise SourceError(f"{path}: no {name} topic with data")
        mid = instance if instance is not None else (0 if 0 in ids else ids[0])
        if (name, mid) not in data:
            raise SourceError(f"{path}: no {name}[{mid}] (instances: {ids})")
        d = data[(name, mid)]
        self.source.label = f"{name}[{mid}]"
        # the GNSS streams not read (another receiver, the other topic): other records
        self.others = {f"{n}[{m}]": len(v.data["timestamp"]) for (n, m), v in data.items()
                       if (n, m) != (name, mid) and "timestamp" in v.data}
        self.types = {f.field_name: f.type_str for f in d.field_data}
        self.data = d.data
        self.n = len(d.data["timestamp"]) if "timestamp" in d.data else 0
        self.lost = self._lost() if self.corrupt else 0
        self.cut = fh.cut_data_id() == d.msg_id  # the file ends inside one of its fixes
        for need in ("time_utc_usec",):
            if need not in self.data:
                raise SourceError(f"{path}: {name} has no {need} field")

    def _lost(self) -> int:
        """GNSS messages missing from the topic: gaps of more than 1.5 intervals."""
        t = self.data.get("timestamp")
        if t is None or len(t) < 3:
            return 1
        dt = np.diff(t.astype(np.int64))
        step = float(np.median(dt))
        if step <= 0:
            return 1
        gaps = dt[dt > 1.5 * step]
        return max(1, int(np.sum(np.rint(gaps / step) - 1)))

    def _column(self, *names: str) -> tuple[str | None, np.ndarray | None]:
        for n in names:
            if n in self.data:
                return n, self.data[n]
        return None, None

    def _degrees(self, *names: str) -> np.ndarray | None:
        name, v = self._column(*names)
        if v is None:
            return None
        if self.types[name].startswith(("int", "uint")):  # 1e-7 degrees
            return np.round(v.astype(np.float64) * 1e-7, 7)
        return v.astype(np.float64)

    def _metres(self, *names: str) -> np.ndarray | None:
        name, v = self._column(*names)
        if v is None:
            return None
        if self.types[name].startswith(("int", "uint")):  # millimetres
            return np.round(v.astype(np.float64) * 1e-3, 3)
        if self.types[name] == "float":
            return np.array([float32_decimal(x) for x in v])
        return v.astype(np.float64)

    def records(self, tally: Tally) -> Iterator[Stamped]:
        for stream, n in self.others.items():
            tally.counts.unknown_types[stream] += n
        if self.corrupt:
            tally.counts.rejected["corrupt_data"] += self.lost
        if self.cut:
            tally.counts.lines += 1
            tally.skip("truncated")
        lat = self._degrees("lat", "latitude_deg")
        lon = self._degrees("lon", "longitude_deg")
        ell = self._metres("alt_ellipsoid", "altitude_ellipsoid_m")
        msl = self._metres("alt", "altitude_msl_m")
        if (ell is not None and msl is not None and self.n
                and np.array_equal(ell, msl) and np.any(ell != 0.0)):
            # PX4's simulators, HIL_GPS and some MAVLink-fed drivers copy the MSL height
            # into the ellipsoidal one: N is tens of metres almost everywhere
            self.source.warn("the ellipsoidal heights equal the MSL heights in every fix: "
                             "a driver without a geoid model; alt_m may be off by the "
                             "local N")
        if lat is None or lon is None or (ell is None and msl is None):
            tally.counts.lines += self.n
            for _ in range(self.n):
                tally.skip("missing_field")
            return
        _, eph = self._column("eph")
        _, epv = self._column("epv")
        fix_type = self.data.get("fix_type")
        sats = self.data.get("satellites_used")
        utc = self.data["time_utc_usec"]
        for i in range(self.n):
            tally.counts.lines += 1
            try:
                if utc[i] == 0:
                    raise Skip("no_utc")
                ft = int(fix_type[i]) if fix_type is not None else None
                if ft is not None and ft not in FIX_TYPES:
                    raise Skip("no_fix")
                e = ell[i] if ell is not None else None
                m = msl[i] if msl is not None else None
                if e is not None and not (e == 0.0 and m is not None and m != 0.0):
                    alt, how = float(e), "ellipsoid"
                else:
                    alt, how = ellipsoidal_m(self.source, None if m is None else float(m),
                                             None, self.options.geoid_offset_m)
                fix = make_fix(
                    lat_deg=float(lat[i]), lon_deg=float(lon[i]), alt_m=alt,
                    acc_m=None if eph is None else float32_decimal(eph[i]),
                    vacc_m=None if epv is None else float32_decimal(epv[i]),
                    fix=FIX_TYPES.get(ft) if ft is not None else None,
                    sats=int(sats[i]) if sats is not None else None,
                    default_acc_m=self.options.default_acc_m,
                )
                tally.heights[how] += 1
                yield Stamped(fix, utc_ns=int(utc[i]) * 1000)
            except Skip as s:
                tally.skip(s.reason)

    def close(self) -> None:
        self.data = {}
