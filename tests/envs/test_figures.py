"""Figures and the rerun recording of a replay, checked by reading them back."""

from __future__ import annotations

import itertools
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


# --------------------------------------------------------------- readability, rendered


@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    """What ``osa run`` replays: three-aps, seed 0, the paper's six modes."""
    import sim

    log = tmp_path_factory.mktemp("three") / "flight.jsonl"
    sim.simulate("three-aps", 0, log)
    return log, replay_logs([log], ReplayOptions(modes=parse_modes("all")))


@pytest.fixture(scope="module")
def no_estimate_run(tmp_path_factory):
    """paper-apaa: the responder never answers, so there is not a single estimate."""
    import sim

    log = tmp_path_factory.mktemp("apaa") / "flight.jsonl"
    sim.simulate("paper-apaa", 0, log)
    return log, replay_logs([log], ReplayOptions(modes=parse_modes("all")))


def _boxes(fig, artists):
    """Display boxes; of a text its letters only (an annotation's box holds its arrow)."""
    from matplotlib.text import Text

    r = fig.canvas.get_renderer()
    return [Text.get_window_extent(a, r) if isinstance(a, Text) else a.get_window_extent(r)
            for a in artists]


def _disjoint(boxes) -> bool:
    return all(not a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1:])


def _all_text(fig) -> list[str]:
    from matplotlib.text import Text

    return [t.get_text() for t in fig.findobj(Text)]


def _labels(ax) -> list:
    from envs.plots import LABEL_GID

    return [t for t in ax.texts if t.get_gid() == LABEL_GID]


def _legend_outside_axes(fig) -> None:
    assert len(fig.legends) == 1
    assert all(ax.get_legend() is None for ax in fig.axes)  # no legend over data
    (leg,) = _boxes(fig, fig.legends)
    for box in _boxes(fig, [ax for ax in fig.axes if ax.axison]):
        assert not leg.overlaps(box)


def test_trajectory_of_the_default_run_reads_well(default_run):
    from envs.plots import RESPONDER_GID, trajectory_figure

    log, rep = default_run
    assert len(rep.truth) == 3
    assert rep.get("a4:77:33:0f:3c:7e", "baseline").status == "no_data"  # AP_AA: no data
    fig = trajectory_figure(rep, [log], "three-aps, seed 0")
    fig.canvas.draw()
    ax = fig.axes[0]
    drawn = sorted(ln.get_gid().split(":", 1)[1] for ln in ax.lines
                   if (ln.get_gid() or "").startswith(RESPONDER_GID))
    assert drawn == sorted(rep.truth)  # every responder, also the one without data
    labels = _labels(ax)
    assert len(labels) == 3 and _disjoint(_boxes(fig, labels))
    assert any("3c:7e" in t.get_text() and "no_data" in t.get_text() for t in labels)
    ax_box = ax.get_window_extent(fig.canvas.get_renderer())
    assert all(ax_box.x0 <= b.x0 and b.x1 <= ax_box.x1 for b in _boxes(fig, labels))
    _legend_outside_axes(fig)
    assert not any("None" in t for t in _all_text(fig))
    import matplotlib.pyplot as plt

    plt.close(fig)


def test_convergence_of_the_default_run_reads_well(default_run):
    from envs.plots import convergence_figure

    _, rep = default_run
    fig = convergence_figure(rep)
    fig.canvas.draw()
    a2 = fig.axes[1]
    curves = {ln.get_label(): ln for ln in a2.lines if not ln.get_label().startswith("_")}
    assert sorted(curves) == sorted(parse_modes("all"))
    looks = {(ln.get_color(), ln.get_linestyle(), ln.get_marker()) for ln in curves.values()}
    assert len(looks) == 6  # colour, style and marker: each mode its own
    base, ema = curves["baseline"], curves["ema"]
    assert base.get_linestyle() != ema.get_linestyle() and base.get_marker() != ema.get_marker()
    assert base.get_linewidth() > 1.5 * ema.get_linewidth()  # EMA drawn on a wider Baseline
    labels = _labels(a2)
    assert len(labels) == 6 and _disjoint(_boxes(fig, labels))
    finals = {t.mode: f"{t.mode} {t.err_h_m:.1f} m" for t in rep.tracks
              if t.bssid == "a4:77:33:0f:1e:02"}
    assert sorted(t.get_text() for t in labels) == sorted(finals.values())
    _legend_outside_axes(fig)
    assert not any("None" in t for t in _all_text(fig))
    import matplotlib.pyplot as plt

    plt.close(fig)


def test_figures_without_estimates_say_so(no_estimate_run):
    import matplotlib.pyplot as plt

    from envs.plots import RESPONDER_GID, convergence_figure, trajectory_figure

    log, rep = no_estimate_run
    assert all(t.estimate is None for t in rep.tracks)
    fig = convergence_figure(rep)
    fig.canvas.draw()
    texts = _all_text(fig)
    assert not any("None" in t for t in texts)
    for ax in fig.axes:
        assert "no estimates" in ax.get_title()
        assert list(ax.get_xticks()) == [] and list(ax.get_yticks()) == []  # no 0-1 axis
        assert not ax.lines
    plt.close(fig)
    fig = trajectory_figure(rep, [log])
    fig.canvas.draw()
    ax, ins = fig.axes
    markers = [ln for ln in ax.lines if (ln.get_gid() or "").startswith(RESPONDER_GID)]
    assert len(markers) == 1 and markers[0].get_markerfacecolor() == "white"
    assert not ins.axison and any("no estimates" in t.get_text() for t in ins.texts)
    assert not any("None" in t for t in _all_text(fig))
    _legend_outside_axes(fig)
    plt.close(fig)


def test_spread_positions_keeps_order_and_gap():
    from envs.plots import spread_positions

    y = [0.50, 0.51, 0.49, 0.95, 0.97, 0.0]
    pos = spread_positions(y, 0.05)
    order = sorted(range(len(y)), key=lambda i: y[i])
    got = [pos[i] for i in order]
    assert all(b - a >= 0.05 - 1e-12 for a, b in itertools.pairwise(got))
    assert 0.0 <= min(pos) and max(pos) <= 1.0
    assert spread_positions([0.2, 0.6], 0.05) == [0.2, 0.6]  # far apart: unchanged
