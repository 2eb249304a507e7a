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


def test_crowded_labels_are_stacked_apart():
    import matplotlib.pyplot as plt

    from envs.plots import place_labels

    fig, ax = plt.subplots(figsize=(4, 4))
    ax.set_xlim(0, 100)
    ax.set_ylim(0, 100)
    fig.canvas.draw()
    pts = [(50 + 0.1 * k, 50, f"responder {k} (vegetation_debris)") for k in range(12)]
    texts = place_labels(ax, pts)
    fig.canvas.draw()
    assert len(texts) == 12 and _disjoint(_boxes(fig, texts))
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


# ------------------------------------------------------- every responder, the ground


def _inside(ax, x: float, y: float, r: float = 0.0) -> bool:
    (x0, x1), (y0, y1) = sorted(ax.get_xlim()), sorted(ax.get_ylim())
    return x0 <= x - r and x + r <= x1 and y0 <= y - r and y + r <= y1


def _gid_lines(ax, prefix: str) -> dict:
    return {ln.get_gid().split(":", 1)[1]: ln for ln in ax.lines
            if (ln.get_gid() or "").startswith(prefix + ":")}


def _ground_artists(fig) -> list:
    from envs.plots import GROUND_GID

    return [a for ax in fig.axes for a in [*ax.images, *ax.collections]
            if a.get_gid() == GROUND_GID]


class ProtocolOnlyTerrain:
    """Nothing but the planner's terrain protocol (as a DEM terrain would offer): a
    plane rising 0.1 m per metre east and 0.05 north, heights from 1-D arrays only."""

    def height_m(self, e_m, n_m):
        e = np.asarray(e_m, dtype=float)
        assert e.ndim == 1  # the figures pass flat arrays
        return 0.1 * e + 0.05 * np.asarray(n_m, dtype=float)

    def sag_curvature(self) -> tuple[float, float]:
        return 0.0, 0.0


def test_trajectory_frames_the_flight_and_zooms_on_every_estimated_responder(default_run):
    import matplotlib.pyplot as plt

    from envs.plots import RESPONDER_GID, gnss_track_enu, trajectory_figure

    log, rep = default_run
    fig = trajectory_figure(rep, [log], "three-aps, seed 0")
    fig.canvas.draw()
    ax = fig.axes[0]
    for b, ln in _gid_lines(ax, RESPONDER_GID).items():
        assert _inside(ax, *ln.get_xydata()[0]), b
    (track,) = gnss_track_enu(rep, [log])
    assert all(_inside(ax, x, y) for x, y in track[:, :2])  # the whole flight
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    span = max(np.ptp(track[:, 0]), np.ptp(track[:, 1]))
    assert max(x1 - x0, y1 - y0) < 1.3 * span  # framed on it, not on a far corner
    # one zoom panel per responder with estimates; every mode's estimate and its whole
    # sigma_H circle in it, the truth on top
    estimated = sorted({t.bssid for t in rep.tracks if t.estimate is not None})
    zooms = {}
    for z in fig.axes[1:]:
        m = _gid_lines(z, RESPONDER_GID)
        if m:
            ((b, ln),) = m.items()
            zooms[b] = (z, ln)
    assert sorted(zooms) == estimated == ["a4:77:33:0f:1e:02", "a4:77:33:0f:2b:a4"]
    for b, (z, truth) in zooms.items():
        assert truth.get_markerfacecolor() == "none"
        circles = [p for p in z.patches]
        tracks = [t for t in rep.tracks if t.bssid == b and t.estimate is not None]
        assert len(circles) == len(tracks) == 6
        for t in tracks:
            e = t.estimate
            assert _inside(z, e.enu_m[0], e.enu_m[1], e.sigma_h_m)
            assert any(np.allclose(c.center, e.enu_m[:2]) and c.radius == e.sigma_h_m
                       for c in circles)
        assert truth.get_zorder() > max(c.get_zorder() for c in circles)
    plt.close(fig)


def test_convergence_of_one_responder_keeps_its_labels_in_the_figure(replay):
    import matplotlib.pyplot as plt

    from envs.plots import convergence_figure

    _, rep = replay
    fig = convergence_figure(rep)
    fig.set_dpi(130)
    fig.canvas.draw()
    labels = [t for a in fig.axes for t in _labels(a)]
    assert len(labels) == 6 and _disjoint(_boxes(fig, labels))
    assert all(b.x1 <= fig.bbox.x1 - 3 for b in _boxes(fig, labels))
    plt.close(fig)


def test_ground_grid_goes_through_the_frames(tmp_path):
    """A replay's frame (at its first fix) is not the world's: heights are looked up
    where the grid point is in the world."""
    from envs.plots import FLAT_RELIEF_M, ground_grid
    from estimator.geodesy import ExactENU, TangentPlaneENU
    from planner.models import FlatTerrain

    world = ExactENU(47.0, 8.0, 400.0)
    lat, lon, h = world.to_geodetic(-100.0, -150.0, 0.0)
    replay = TangentPlaneENU(lat, lon, h)  # 100 m west, 150 m south of the origin
    g = ground_grid(ProtocolOnlyTerrain(), (-50.0, 250.0, -40.0, 60.0), terrain_frame=world,
                    plot_frame=replay)
    ee, nn = np.meshgrid(g.e_m, g.n_m)
    assert g.e_m[0] == -50.0 and g.e_m[-1] == 250.0 and g.n_m[-1] == 60.0
    # the world is 100 m east, 150 m north of the replay's (eq. 1's tangent plane and
    # exact ENU agree to ~0.2 % over these distances: 0.1 m in height here, not 12.5 m)
    expected = 0.1 * (ee - 100.0) + 0.05 * (nn - 150.0)
    assert np.max(np.abs(g.height_m - expected)) < 0.1
    same = ground_grid(ProtocolOnlyTerrain(), (-50.0, 250.0, -40.0, 60.0))
    assert np.max(np.abs(same.height_m - (0.1 * ee + 0.05 * nn))) < 1e-12
    # flat: nothing to draw, whatever the level; relief just above the threshold: drawn
    assert ground_grid(FlatTerrain(12.0), (0.0, 100.0, 0.0, 100.0)) is None
    assert ground_grid(None, (0.0, 100.0, 0.0, 100.0)) is None
    # relief 0.1 de + 0.05 dn: just under the threshold, then just over it
    assert ground_grid(ProtocolOnlyTerrain(), (0.0, 0.9 * 5 * FLAT_RELIEF_M, 0.0,
                                               0.9 * 10 * FLAT_RELIEF_M)) is None
    assert ground_grid(ProtocolOnlyTerrain(), (0.0, 1.1 * 5 * FLAT_RELIEF_M, 0.0,
                                               1.1 * 10 * FLAT_RELIEF_M)) is not None


@pytest.mark.parametrize("kind", ["hills", "grid", "protocol", "flat"])
def test_run_trajectory_draws_the_ground_of_every_terrain_kind(default_run, kind):
    import matplotlib.pyplot as plt

    import sim
    from envs.plots import GROUND_GID, trajectory_figure
    from planner.models import FlatTerrain

    log, rep = default_run
    world = sim.realise(sim.load_scenario("three-aps"), 0).world
    terrain = {"hills": world.terrain,
               "grid": sim.GridTerrain(np.add.outer(np.arange(30.0), np.arange(30.0)),
                                       e0_m=-600.0, n0_m=-600.0, spacing_m=40.0),
               "protocol": ProtocolOnlyTerrain(), "flat": FlatTerrain(5.0)}[kind]
    fig = trajectory_figure(rep, [log], terrain=terrain, terrain_frame=world.frame)
    fig.canvas.draw()
    ground = _ground_artists(fig)
    bars = [a for a in fig.axes if a.get_gid() == GROUND_GID]
    if kind == "flat":
        assert not ground and not bars
    else:
        ax = fig.axes[0]
        (img,) = ax.images
        assert img.get_gid() == GROUND_GID and img.get_zorder() < min(
            ln.get_zorder() for ln in ax.lines)  # under the tracks
        assert len(ground) == 2  # the hillshade and the contours
        (bar,) = bars
        assert "ground height (m)" in bar.get_ylabel()
        lo, hi = bar.get_ylim()
        assert hi - lo > 1.0
        # light: the ground keeps the tracks readable
        assert np.asarray(img.get_array())[..., :3].min() > 0.45
    plt.close(fig)


def test_convergence_has_a_column_per_responder(default_run):
    import matplotlib.pyplot as plt

    from envs.plots import convergence_figure

    _, rep = default_run
    fig = convergence_figure(rep)
    fig.canvas.draw()
    titles = [a.get_title() for a in fig.axes]
    for short in ("1e:02", "2b:a4"):
        assert sum(short in t for t in titles) == 2  # (a) sigma_H and (b) error
    empty = [a for a in fig.axes if not a.axison]
    assert len(empty) == 1 and "3c:7e" in empty[0].texts[0].get_text()
    assert "no estimates" in empty[0].texts[0].get_text()
    labels = [t for a in fig.axes for t in _labels(a)]
    assert len(labels) == 12 and _disjoint(_boxes(fig, labels))
    finals = sorted(f"{t.mode} {t.err_h_m:.1f} m" for t in rep.tracks if t.err_h_m is not None)
    assert sorted(t.get_text() for t in labels) == finals
    # each label points at its mode's reported estimate (the last stable one)
    by_text = {(t.bssid, f"{t.mode} {t.err_h_m:.1f} m"): t for t in rep.tracks if t.history}
    for a in fig.axes:
        b = next((b for b in ("1e:02", "2b:a4") if b in a.get_title()), None)
        for lab in _labels(a):
            (trk,) = [t for (bs, txt), t in by_text.items()
                      if bs.endswith(b) and txt == lab.get_text()]
            assert lab.xy == pytest.approx((trk.estimate.t_s - trk.bootstrap_t_s, trk.err_h_m))
    # the leader lines start at the labels' left edge: none runs through a label
    r = fig.canvas.get_renderer()
    for lab, box in zip(labels, _boxes(fig, labels), strict=True):
        assert lab.arrow_patch.get_window_extent(r).x1 <= box.x0 + 2.0
    _legend_outside_axes(fig)
    # saving draws again (at another dpi): the labels stay apart and inside the figure
    fig.set_dpi(130)
    fig.canvas.draw()
    assert _disjoint(_boxes(fig, labels))
    assert all(b.x1 <= fig.bbox.x1 - 3 for b in _boxes(fig, labels))
    for lab in labels:  # none over another panel
        box = _boxes(fig, [lab])[0]
        own = lab.axes
        assert not any(box.overlaps(b) for b in _boxes(fig, [a for a in fig.axes
                                                              if a is not own and a.axison]))
    plt.close(fig)


# ----------------------------------------------------------------------------- search


@pytest.fixture(scope="module")
def search_result():
    """search-three-mixed, adaptive, seed 0, 7 minutes: two estimates, one never heard."""
    import dataclasses

    import sim
    from envs.loop import run_search
    from envs.policies import load_policy

    sc = sim.load_scenario("search-three-mixed")
    sc = dataclasses.replace(sc, search=dataclasses.replace(sc.search, budget_s=420.0))
    res = run_search(sc, load_policy("adaptive", sc), 0)
    return res, sim.realise(sc, 0).world.terrain


def test_search_trajectory_shows_estimate_circle_and_truth(search_result):
    import matplotlib.pyplot as plt

    from envs.plots import RESPONDER_GID
    from envs.search_plots import R95_GID, search_trajectory_figure

    res, terrain = search_result
    assert len(res.estimates_enu_m) == 2 and len(res.truth_enu_m) == 3
    fig = search_trajectory_figure(res, terrain=terrain)
    fig.canvas.draw()
    ax = fig.axes[0]
    truths = _gid_lines(ax, RESPONDER_GID)
    assert sorted(truths) == sorted(res.truth_enu_m)
    circles = {p.get_gid().split(":", 1)[1]: p for p in ax.patches
               if (p.get_gid() or "").startswith(R95_GID + ":")}
    assert sorted(circles) == sorted(res.estimates_enu_m)
    by = {r["bssid"]: r for r in res.responders}
    for tr in truths.values():
        assert tr.get_markerfacecolor() == "none"  # open: nothing under it is hidden
        assert _inside(ax, *tr.get_xydata()[0])
    for b, c in circles.items():
        assert c.radius == by[b]["r95_h_m"] and not c.get_fill()
        assert c.get_zorder() > truths[b].get_zorder()
        est = [ln for ln in ax.lines if np.allclose(ln.get_xydata()[0],
                                                    res.estimates_enu_m[b][:2])]
        assert est and min(ln.get_zorder() for ln in est) > truths[b].get_zorder()
    # framed on the area: the whole area in view, at most a 10 % margin
    area = np.asarray(res.area_enu_m)
    lo, hi = area.min(axis=0), area.max(axis=0)
    pad = 0.1 * (hi - lo)
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    assert lo[0] - pad[0] <= x0 <= lo[0] and hi[0] <= x1 <= hi[0] + pad[0]
    assert lo[1] - pad[1] <= y0 <= lo[1] and hi[1] <= y1 <= hi[1] + pad[1]
    # a zoom per estimate: the whole circle and the truth in view
    zooms = [a for a in fig.axes[1:] if a.patches]
    assert len(zooms) == 2
    for z in zooms:
        (c,) = z.patches
        b = c.get_gid().split(":", 1)[1]
        assert _inside(z, *c.center, c.radius) and _inside(z, *res.truth_enu_m[b][:2])
    assert len(_ground_artists(fig)) == 2
    assert _disjoint(_boxes(fig, _labels(ax)))
    assert len(fig.legends) == 1 and "95 % circle" in " ".join(
        t.get_text() for t in fig.legends[0].get_texts())
    plt.close(fig)


def test_search_errors_list_every_responder(search_result):
    import matplotlib.pyplot as plt

    from envs.search_plots import search_error_figure

    res, _ = search_result
    fig = search_error_figure(res)
    words = " ".join(t.get_text() for t in fig.axes[0].get_legend().get_texts())
    for b in res.truth_enu_m:
        assert b[-5:] in words
    assert "never heard" in words  # ba:35:20:fb:6c:b3 answered nothing
    fig.canvas.draw()
    ticks = [t.get_text() for t in fig.axes[0].get_yticklabels() if t.get_text()]
    assert ticks and all(t.replace(".", "").isdigit() for t in ticks)  # 0.5, 1, 2: plain
    plt.close(fig)


def test_search_circle_falls_back_to_sigma_and_flat_ground_is_skipped(search_result):
    import dataclasses

    import matplotlib.pyplot as plt

    from envs.plots import r95_radius_m
    from envs.search_plots import R95_GID, search_trajectory_figure
    from planner.models import FlatTerrain

    assert r95_radius_m(3.0, 2.0) == 3.0
    assert r95_radius_m(None, 2.0) == pytest.approx(4.9)
    assert r95_radius_m(math.nan, 2.0) == pytest.approx(4.9)
    assert r95_radius_m(None, None) is None
    res, _ = search_result
    plain = [{k: v for k, v in r.items() if k != "r95_h_m"} for r in res.responders]
    fig = search_trajectory_figure(dataclasses.replace(res, responders=plain),
                                   terrain=FlatTerrain(3.0))
    circles = [p for p in fig.axes[0].patches if (p.get_gid() or "").startswith(R95_GID)]
    sig = {r["bssid"]: r["sigma_h_m"] for r in plain if r.get("sigma_h_m") is not None}
    assert sorted(c.radius for c in circles) == pytest.approx(sorted(2.45 * s
                                                                     for s in sig.values()))
    assert not _ground_artists(fig)
    plt.close(fig)


# --------------------------------------------------------------------------- evaluate


@pytest.fixture(scope="module")
def evaluation():
    import dataclasses

    import sim
    from envs.evaluate import evaluate

    sc = sim.load_scenario("search-random-los-rtk")
    sc = dataclasses.replace(sc, search=dataclasses.replace(sc.search, budget_s=240.0))
    ev = evaluate(sc, ["lawnmower", "adaptive", "expanding-square"], [0, 1],
                  example_seeds=[0, 1])
    return ev, sim.realise(sc, 0).world.terrain


def test_evaluate_trajectories_mark_each_policy_on_the_area(evaluation):
    import matplotlib.pyplot as plt

    from envs.evaluate_plots import trajectories_figure

    ev, terrain = evaluation
    fig = trajectories_figure(ev, terrain=terrain)
    fig.canvas.draw()
    panels = [a for a in fig.axes if a.get_title().startswith("seed")]
    assert len(panels) == 2
    area = np.asarray(ev.area_enu_m)
    lo, hi = area.min(axis=0), area.max(axis=0)
    for ax in panels:
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        pad = 0.1 * (hi - lo)
        assert lo[0] - pad[0] <= x0 <= lo[0] and hi[0] <= x1 <= hi[0] + pad[0]
        assert lo[1] - pad[1] <= y0 <= lo[1] and hi[1] <= y1 <= hi[1] + pad[1]
        looks = {}
        for p in ev.policies:
            (est,) = [ln for ln in ax.lines if ln.get_gid() == f"estimate:{p}"]
            looks[p] = (est.get_marker(), est.get_color())
            assert _inside(ax, *est.get_xydata()[0])
        assert len({m for m, _ in looks.values()}) == 3  # a marker each
        assert len({c for _, c in looks.values()}) == 3  # a colour each
        legend = ax.get_legend()
        texts = [t.get_text() for t in legend.get_texts()]
        assert [t.split(" (")[0] for t in texts] == list(ev.policies)
        # the legend's line shows the same marker and colour as the estimates
        for h, p in zip(legend.legend_handles, ev.policies, strict=True):
            assert (h.get_marker(), h.get_color()) == looks[p]
    assert len(_ground_artists(fig)) == 4  # image and contours in each panel
    plt.close(fig)
    from planner.models import FlatTerrain

    fig = trajectories_figure(ev, terrain=FlatTerrain())
    assert not _ground_artists(fig)
    plt.close(fig)


# ----------------------------------------------------------------------------- render


def test_env_render_has_axes_legend_and_flight_time():
    import dataclasses

    import gymnasium

    import envs  # noqa: F401
    import sim
    from envs.gym.render import LEGEND_GID, map_figure, map_image

    sc = sim.load_scenario("search-random-los")
    sc = dataclasses.replace(sc, search=dataclasses.replace(sc.search, budget_s=600.0))
    env = gymnasium.make("osa/Search-v0", scenario=sc, render_mode="rgb_array")
    env.reset(seed=0)
    loop = env.unwrapped.loop
    for k in range(120):
        env.step((0, 3, 1, 4, 3, 2)[k % 6])
        if any(loop.estimate(b).lat_deg is not None for b in loop.truth):
            break
    assert any(loop.estimate(b).lat_deg is not None for b in loop.truth)
    fig = map_figure(loop, env.unwrapped.pilot)
    ax = fig.axes[0]
    assert "(m)" in ax.get_xlabel() and "(m)" in ax.get_ylabel()
    (legend,) = [leg for leg in fig.legends if leg.get_gid() == LEGEND_GID]
    words = " ".join(t.get_text() for t in legend.get_texts())
    for what in ("search area", "path", "estimate", "95 % circle", "heard"):
        assert what in words
    assert any(f"flight time {loop.t_s / 60:.1f} min" in t.get_text() for t in fig.texts)
    fig.canvas.draw()
    (box,) = _boxes(fig, [legend])
    assert not box.overlaps(ax.get_window_extent(fig.canvas.get_renderer()))
    img = map_image(loop, env.unwrapped.pilot)
    assert img.shape == (480, 720, 3) and img.dtype == np.uint8
    env.close()


# ----------------------------------------------------------------------------- tables


def _columns_line_up(lines: list[str], rows: list[tuple], aligns: str, titles: list[str]):
    """Every cell sits under its title: left-aligned cells start where the title starts,
    right-aligned ones end where it ends."""
    head = lines[0]
    spans, at = [], 0
    for t in titles:
        s = head.index(t, at)
        spans.append((s, s + len(t)))
        at = s + len(t)
    for line, row in zip(lines[1:], rows, strict=True):
        for (s, e), a, cell in zip(spans, aligns, row, strict=True):
            if a == "<":
                assert line[s:s + len(cell)] == cell, (line, cell)
                assert s == 0 or line[s - 1] == " "
            else:
                assert line[e - len(cell):e] == cell, (line, cell)
                assert line[e - len(cell) - 1] == " "


def test_text_table_widens_columns_for_long_cells():
    from estimator.tables import Column, text_table

    cols = [Column("name", "<", 6), Column("n", ">", 4), Column("tag", "<", 0)]
    short = text_table(cols, [("ab", "1", "x")])
    assert short == ["name     n tag", "ab       1 x"]  # least widths kept
    rows = [("a-very-long-name", "12345678", "t"), ("b", "2", "longer-tag")]
    lines = text_table(cols, rows, indent="  ", rule="=")
    assert lines[1] == "  " + "=" * (len(lines[0]) - 2)
    _columns_line_up([lines[0], *lines[2:]], rows, "<><", ["name", "n", "tag"])
    with pytest.raises(ValueError, match="cells"):
        text_table(cols, [("a", "b")])


def test_replay_table_keeps_columns_with_long_modes(default_run, monkeypatch):
    import dataclasses

    from estimator.modes import MODES
    from estimator.pipeline import ModeSpec
    from estimator.replay import format_table

    _, rep = default_run
    monkeypatch.setitem(MODES, "adaptive-r-robust-x", ModeSpec("adaptive-r-robust-x"))
    long = dataclasses.replace(rep, tracks=[dataclasses.replace(t, mode="adaptive-r-robust-x")
                                            if t.mode == "ema" else t for t in rep.tracks])
    text = format_table(long)
    # every block: the header, then its rows; all blocks share one layout
    blocks = [b.splitlines()[1:] for b in text.split("\n\n")[:3]]
    titles = ["Mode", "status", "n_gate", "n_acc", "sigma_H"]
    for lines in blocks:
        rows = [tuple(line.split()[:5]) for line in lines[1:]]
        _columns_line_up(lines, rows, "<<>>>", titles)
        assert lines[0] == blocks[0][0]
    assert "adaptive-r-robust-x" in text
    # short names: the paper-style layout exactly as before
    plain = format_table(rep).splitlines()
    assert plain[1] == ("  Mode        status         n_gate  n_acc  sigma_H  sigma_Z  err_2D"
                        "    TWM  err_3D   bias")
    assert plain[2].startswith("  baseline    converged          78    310")


def test_evaluate_summary_keeps_columns_with_long_policy_names():
    from envs.evaluate import PolicySummary, format_summary

    def s(name, n):
        return PolicySummary(name, n, 3 * n, n, 1 / 3, 100.0, 900.0, False, True, n, 1.234,
                             12.5, 1, 60.0, False)

    names = ["adaptive", "ppo:models/search-ppo-final-checkpoint.zip", "lawnmower"]
    lines = format_summary([s(p, k + 1) for k, p in enumerate(names)]).splitlines()
    assert set(lines[1]) == {"-"} and len(lines[1]) == len(lines[0])
    rows = [(p, str(k + 1), f"{k + 1}/{3 * (k + 1)}  33%", "1.7", ">=15.0", "1.23", "12.50",
             "1", "1.0") for k, p in enumerate(names)]
    _columns_line_up([lines[0], *lines[2:]], rows, "<>>>>>>>>",
                     ["policy", "seeds", "localised", "t_loc med", "t_loc p90", "err med",
                      "err p90", "<=1 m", "t_1m med"])
    short = format_summary([s("adaptive", 30)]).splitlines()
    assert short[0] == ("policy               seeds     localised  t_loc med  t_loc p90  "
                        "err med  err p90  <=1 m  t_1m med")
    assert short[2] == ("adaptive                30    30/90  33%        1.7     >=15.0     "
                        "1.23    12.50      1       1.0")


def test_search_summary_keeps_columns_with_long_bssids():
    from types import SimpleNamespace

    from envs.commands.search import summary

    resp = [
        {"bssid": "a4:77:33:0f:1e:02", "concealment": "open", "detected_at_s": 84.0,
         "localised_at_s": 240.0, "status": "converged", "sigma_h_m": 1.83, "err_h_m": 1.31},
        {"bssid": "agent-2/a4:77:33:0f:1e:02:extra", "concealment": "vegetation_and_rubble",
         "detected_at_s": 1500.0, "status": "weak_geometry_and_more", "sigma_h_m": 12.345},
        {"bssid": "ba:35:20:fb:6c:b3", "concealment": "vegetation_debris", "status": "no_data"},
    ]
    res = SimpleNamespace(scenario="s", seed=0, policy="p", mode="refined", ended="budget",
                          flight_time_s=1500.0, path_length_m=9710.0, replans=3,
                          responders=resp)
    lines = summary(res).splitlines()[1:]
    rows = [("a4:77:33:0f:1e:02", "open", "1.4 min", "4.0 min", "converged", "1.83", "1.31"),
            ("agent-2/a4:77:33:0f:1e:02:extra", "vegetation_and_rubble", "25.0 min", "-",
             "weak_geometry_and_more", "12.35", "-"),
            ("ba:35:20:fb:6c:b3", "vegetation_debris", "-", "-", "no_data", "-", "-")]
    _columns_line_up(lines, rows, "<<>>>>>", ["responder", "class", "heard", "localised",
                                              "status", "sigma_H", "err_2D"])
    short = summary(SimpleNamespace(**{**vars(res), "responders": [resp[0], resp[2]]}))
    assert short.splitlines()[1:] == [
        "  responder         class                 heard  localised         status  sigma_H"
        "  err_2D",
        "  a4:77:33:0f:1e:02 open                1.4 min    4.0 min      converged     1.83"
        "    1.31",
        "  ba:35:20:fb:6c:b3 vegetation_debris         -          -        no_data        -"
        "       -",
    ]
