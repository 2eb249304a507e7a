"""rerun visualisation of a replay: flight, responders, estimates and their uncertainty.

One entity path per thing, units in names:
``world/drone/track`` (GNSS path), ``world/ap/<bssid>/truth``,
``world/ap/<bssid>/<mode>/estimate`` (point + 1-sigma ellipsoid), and time series
``plots/<bssid>/<mode>/sigma_h_m`` and ``.../err_h_m`` on the ``flight_time`` timeline.
Wall-clock log time is disabled, so the same replay gives the same recording.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from envs.plots import MODE_COLOURS, gnss_track_enu
from estimator.replay import ReplayReport

_RGB = {
    "tab:blue": (31, 119, 180), "tab:orange": (255, 127, 14), "tab:green": (44, 160, 44),
    "tab:red": (214, 39, 40), "tab:purple": (148, 103, 189), "tab:brown": (140, 86, 75),
    "black": (20, 20, 20), "gray": (128, 128, 128),
}


def record_replay(
    report: ReplayReport, log_paths: Sequence[str | Path], path: str | Path
) -> Path:
    """Write a rerun ``.rrd`` recording of a replay (history kept by the replay)."""
    import rerun as rr

    rec = rr.RecordingStream("osa-testbed", recording_id="osa-replay", send_properties=False)
    rec.set_log_time_enabled(False)
    rec.save(str(path))
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    for k, trk in enumerate(gnss_track_enu(report, log_paths)):
        rec.log(f"world/drone/track_{k}", rr.LineStrips3D([trk], colors=[(120, 120, 120)]),
                static=True)
    t_ref = None
    for t in report.tracks:
        if t.history:
            t0 = t.history[0].t_s
            t_ref = t0 if t_ref is None else min(t_ref, t0)
    for t in report.tracks:
        base = f"world/ap/{t.bssid.replace(':', '')}"
        if t.truth_enu_m is not None:
            rec.log(f"{base}/truth", rr.Points3D([t.truth_enu_m], colors=[(255, 215, 0)],
                                                 radii=[0.8], labels=[t.bssid]), static=True)
        colour = _RGB.get(MODE_COLOURS.get(t.mode, "gray"), (128, 128, 128))
        series = f"plots/{t.bssid.replace(':', '')}/{t.mode}"
        for p in t.history:
            rec.set_time("flight_time", duration=p.t_s - (t_ref or 0.0))
            s = p.sigma_h_m / math.sqrt(2.0)
            rec.log(f"{base}/{t.mode}/estimate",
                    rr.Ellipsoids3D(centers=[p.enu_m], half_sizes=[[s, s, p.sigma_z_m]],
                                    colors=[colour]))
            rec.log(f"{series}/sigma_h_m", rr.Scalars([p.sigma_h_m]))
            if t.truth_enu_m is not None:
                tr = t.truth_enu_m
                rec.log(f"{series}/err_h_m",
                        rr.Scalars([float(np.hypot(p.enu_m[0] - tr[0], p.enu_m[1] - tr[1]))]))
    rec.flush()
    rec.disconnect()
    return Path(path)


def record_search(result, path: str | Path) -> Path:
    """Write a rerun ``.rrd`` recording of a closed-loop search (``osa search --rerun``):
    ``world/area``, ``world/drone/<agent>`` (the autopilot's position over time),
    ``world/responders/<bssid>/truth``, and per responder the time series
    ``plots/<bssid>/sigma_h_m``, ``.../r95_h_m``, ``.../err_h_m`` on ``flight_time``."""
    import rerun as rr

    rec = rr.RecordingStream("osa-testbed", recording_id="osa-search", send_properties=False)
    rec.set_log_time_enabled(False)
    rec.save(str(path))
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    area = np.asarray((*result.area_enu_m, result.area_enu_m[0]), dtype=float)
    rec.log("world/area", rr.LineStrips3D([np.column_stack([area, np.zeros(len(area))])],
                                          colors=[(0, 0, 0)]), static=True)
    for b, p in result.truth_enu_m.items():
        rec.log(f"world/responders/{b.replace(':', '')}/truth",
                rr.Points3D([p], colors=[(255, 215, 0)], radii=[1.5], labels=[b]), static=True)
    for k, trk in enumerate(result.nav_track):
        for row in trk[::2]:
            rec.set_time("flight_time", duration=row[0])
            rec.log(f"world/drone/{k}", rr.Points3D([row[1:4]], radii=[1.0],
                                                    colors=[(40, 40, 200)]))
    for b, pts in result.series.items():
        base = f"plots/{b.replace(':', '')}"
        for p in pts:
            rec.set_time("flight_time", duration=p.t_s)
            for name in ("sigma_h_m", "r95_h_m", "err_h_m"):
                v = getattr(p, name)
                if v is not None and math.isfinite(v):
                    rec.log(f"{base}/{name}", rr.Scalars([v]))
    rec.flush()
    rec.disconnect()
    return Path(path)
