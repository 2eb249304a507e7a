"""Real flights in: readers of recorder files and the joiner that writes a flight log.

``osa import`` (docs/import.md) turns a GNSS file and a ranging file into one flight
log (docs/log-format.md). One module per format reads its files with the field's own
library where the format is binary (pyulog, pymavlink's DFReader, rosbags) and yields
log records with their clock facts (:class:`estimator.importers.common.Stamped`);
:mod:`estimator.importers.joiner` recognises the formats, puts both files on one time
axis and writes the span they share.

GNSS: ``gnsslogger``, ``ulog``, ``dataflash``, ``rosbag2``, ``nmea``.
Ranging: ``android-csv``, ``sensorreadout``.
"""

from estimator.importers.joiner import (
    FORMATS,
    GNSS_FORMATS,
    RANGES_FORMATS,
    ImportOptions,
    ImportRefused,
    ImportReport,
    detect_format,
    import_flight,
)

__all__ = [
    "FORMATS",
    "GNSS_FORMATS",
    "RANGES_FORMATS",
    "ImportOptions",
    "ImportRefused",
    "ImportReport",
    "detect_format",
    "import_flight",
]
