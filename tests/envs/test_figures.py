"""Figures and the rerun recording of a replay, checked by reading them back."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envs.plots import plot_convergence, plot_trajectory
from envs.viz import record_replay
from estimator.replay import ReplayOptions, parse_modes, replay_logs
from tests.estimator.synth import write_flight


@pytest.fixture(scope="module")
def replay(tmp_path_factory):
    log = write_flight(tmp_path_factory.mktemp("fig") / "f.jsonl", seed=8, duration_s=120.0)
    return log, replay_logs([log], ReplayOptions(modes=parse_modes("all")))


def test_pngs_are_written(replay, tmp_path):
    import matplotlib.image as mpimg

    log, rep = replay
    a = plot_trajectory(rep, [log], tmp_path / "t.png")
    b = plot_convergence(rep, tmp_path / "c.png")
    for p in (a, b):
        img = mpimg.imread(p)
        assert img.shape[0] > 500 and img.shape[1] > 800
        assert img[..., :3].std() > 0.05  # not a blank canvas


def test_rerun_recording_reads_back(replay, tmp_path):
    from rerun.chunk import RrdReader

    log, rep = replay
    path = record_replay(rep, [log], tmp_path / "r.rrd")
    rows: dict[str, int] = {}
    for c in RrdReader(str(path)).stream().to_chunks():
        rows[str(c.entity_path)] = rows.get(str(c.entity_path), 0) + c.num_rows
    b = rep.tracks[0].bssid.replace(":", "")
    assert f"/world/ap/{b}/truth" in rows
    assert any(k.startswith("/world/drone/track") for k in rows)
    for t in rep.tracks:
        # one estimate and one sigma_H sample per published estimate
        assert rows[f"/world/ap/{b}/{t.mode}/estimate"] == len(t.history)
        assert rows[f"/plots/{b}/{t.mode}/sigma_h_m"] == len(t.history)
    assert math.isfinite(np.mean([len(t.history) for t in rep.tracks]))


def test_figures_of_a_flight_without_usable_ranges(tmp_path):
    """No associated range (all responses failed): the path and responders still show."""
    import json

    from envs.plots import gnss_track_enu, with_plot_frame

    log = write_flight(tmp_path / "f.jsonl", seed=9, duration_s=30.0)
    lines = log.read_text().splitlines()
    out = []
    for line in lines:
        obj = json.loads(line)
        if obj["type"] == "rtt":
            obj = {"type": "rtt", "t_ns": obj["t_ns"], "bssid": obj["bssid"],
                   "status": "no_response"}
        out.append(json.dumps(obj))
    log.write_text("\n".join(out) + "\n")
    rep = replay_logs([log], ReplayOptions(modes=("baseline",)))
    assert rep.frame is None and rep.tracks[0].status == "no_data"
    shown = with_plot_frame(rep, [log])
    assert shown.frame is not None
    tr = shown.tracks[0].truth_enu_m
    (path,) = gnss_track_enu(shown, [log])
    # frame at the first fix, (50, 0) m in the synthetic frame; the AP is at (25, -10) m
    assert np.hypot(tr[0] + 25.0, tr[1] + 10.0) < 0.5
    assert np.hypot(*path[0, :2]) < 1e-9
    assert plot_trajectory(rep, [log], tmp_path / "t.png").stat().st_size > 10_000
    assert plot_convergence(rep, tmp_path / "c.png").stat().st_size > 10_000
