"""ENU frames: eq. (1) tangent plane against a hand computation and the exact WGS84 ENU."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.geodesy import EARTH_RADIUS_M, ExactENU, TangentPlaneENU, make_frame

PAPER_ORIGIN = (36.715, -4.478, 100.0)  # the paper's test site latitude

# WGS84, for the model of the tangent plane's scale error
_A = 6378137.0
_F = 1.0 / 298.257223563
_E2 = _F * (2.0 - _F)


def _radii(lat_deg: float) -> tuple[float, float]:
    """Meridional (M) and prime-vertical (N) radii of curvature of WGS84 at ``lat_deg``."""
    s2 = math.sin(math.radians(lat_deg)) ** 2
    w = 1.0 - _E2 * s2
    return _A * (1.0 - _E2) / w**1.5, _A / math.sqrt(w)


# --------------------------------------------------------------------- eq. (1) by hand


def test_tangent_plane_matches_eq1_by_hand() -> None:
    fr = TangentPlaneENU(*PAPER_ORIGIN)
    x, y, z = fr.to_enu(36.716, -4.477, 110.0)  # 0.001 deg north and east, 10 m up
    # x = R * radians(0.001) * cos(mean lat), y = R * radians(0.001), z = h - h0
    r_dtheta = 6378137.0 * (0.001 * math.pi / 180.0)
    assert r_dtheta == pytest.approx(111.31949079327357, abs=1e-9)
    cos_mean = math.cos(math.radians(36.7155))
    assert cos_mean == pytest.approx(0.8016139417461521, abs=1e-15)
    assert x == pytest.approx(r_dtheta * cos_mean, abs=1e-6)
    assert x == pytest.approx(89.235255808, abs=1e-6)
    assert y == pytest.approx(r_dtheta, abs=1e-6)
    assert y == pytest.approx(111.319490793, abs=1e-6)
    assert z == 10.0
    # the cosine is of the MEAN latitude: the origin's would be 0.58 mm off, which the
    # 1e-6 m checks above tell apart
    assert abs(x - r_dtheta * math.cos(math.radians(36.715))) == pytest.approx(5.8e-4, abs=1e-5)
    assert fr.to_geodetic(x, y, z) == pytest.approx((36.716, -4.477, 110.0), abs=1e-12)


def test_tangent_plane_south_west_and_origin() -> None:
    fr = TangentPlaneENU(*PAPER_ORIGIN)
    assert fr.to_enu(*PAPER_ORIGIN) == (0.0, 0.0, 0.0)
    x, y, z = fr.to_enu(36.714, -4.479, 95.5)
    r_dtheta = EARTH_RADIUS_M * math.radians(0.001)
    assert x == pytest.approx(-r_dtheta * math.cos(math.radians(36.7145)), abs=1e-6)
    assert x == pytest.approx(-89.236417337, abs=1e-6)
    assert y == pytest.approx(-r_dtheta, abs=1e-6)
    assert z == -4.5


def test_make_frame() -> None:
    assert isinstance(make_frame("tangent", *PAPER_ORIGIN), TangentPlaneENU)
    assert isinstance(make_frame("wgs84", *PAPER_ORIGIN), ExactENU)
    with pytest.raises(ValueError, match="unknown projection"):
        make_frame("utm", *PAPER_ORIGIN)


# --------------------------------------------------------------------- round trips

_origins = st.tuples(
    st.floats(min_value=-80.0, max_value=80.0),
    st.floats(min_value=-180.0, max_value=180.0),
    st.floats(min_value=-400.0, max_value=5000.0),
)
_offsets = st.tuples(
    st.floats(min_value=-5000.0, max_value=5000.0),
    st.floats(min_value=-5000.0, max_value=5000.0),
    st.floats(min_value=-500.0, max_value=500.0),
).filter(lambda o: math.hypot(o[0], o[1]) <= 5000.0)


@settings(max_examples=300, deadline=None)
@given(origin=_origins, off=_offsets)
def test_tangent_round_trip_to_1e_9_deg(origin, off) -> None:
    # a point within 5 km of the origin, in valid WGS84 (longitude in [-180, 180])
    lat, lon, h = ExactENU(*origin).to_geodetic(*off)
    assert -180.0 <= lon <= 180.0
    fr = TangentPlaneENU(*origin)
    e, n, u = fr.to_enu(lat, lon, h)
    assert math.hypot(e, n) < 5100.0  # a short vector, also across the antimeridian
    lat2, lon2, h2 = fr.to_geodetic(e, n, u)
    assert abs(lat2 - lat) < 1e-9
    assert abs((lon2 - lon + 180.0) % 360.0 - 180.0) < 1e-9  # (+-180 deg is one meridian)
    assert -180.0 <= lon2 <= 180.0
    assert abs(h2 - h) < 1e-9
    # and the other way: metres -> degrees -> metres
    e2, n2, u2 = fr.to_enu(*fr.to_geodetic(*off))
    assert np.allclose((e2, n2, u2), off, rtol=0, atol=1e-6)


@settings(max_examples=150, deadline=None)
@given(origin=_origins, off=_offsets)
def test_exact_round_trip_to_1e_6_m(origin, off) -> None:
    fr = ExactENU(*origin)
    geo = fr.to_geodetic(*off)
    back = fr.to_enu(*geo)
    assert all(isinstance(v, float) for v in back)
    assert math.dist(back, off) < 1e-6


@pytest.mark.parametrize(
    ("cls", "atol_m", "atol_deg"), [(TangentPlaneENU, 1e-9, 1e-12), (ExactENU, 1e-8, 1e-12)]
)
def test_scalar_and_array_inputs_agree(cls, atol_m: float, atol_deg: float) -> None:
    rng = np.random.default_rng(4)
    fr = cls(*PAPER_ORIGIN)
    lat = PAPER_ORIGIN[0] + rng.uniform(-0.01, 0.01, 50)
    lon = PAPER_ORIGIN[1] + rng.uniform(-0.01, 0.01, 50)
    alt = PAPER_ORIGIN[2] + rng.uniform(-50, 50, 50)
    ea, na, ua = fr.to_enu(lat, lon, alt)
    assert ea.shape == na.shape == ua.shape == (50,)
    pts = zip(lat, lon, alt, strict=True)
    scalar = np.array([fr.to_enu(float(a), float(b), float(c)) for a, b, c in pts])
    assert all(isinstance(v, float) for v in fr.to_enu(float(lat[0]), float(lon[0]), 1.0))
    np.testing.assert_allclose(scalar, np.c_[ea, na, ua], rtol=0, atol=atol_m)
    la, lo, hh = fr.to_geodetic(ea, na, ua)
    enu = zip(ea, na, ua, strict=True)
    back = np.array([fr.to_geodetic(float(e), float(n), float(u)) for e, n, u in enu])
    np.testing.assert_allclose(back[:, :2], np.c_[la, lo], rtol=0, atol=atol_deg)
    np.testing.assert_allclose(back[:, 2], hh, rtol=0, atol=atol_m)
    np.testing.assert_allclose(np.c_[la, lo], np.c_[lat, lon], rtol=0, atol=1e-9)
    np.testing.assert_allclose(hh, alt, rtol=0, atol=atol_m)
    # lists are arrays too
    el, nl, ul = fr.to_enu(list(lat), list(lon), list(alt))
    np.testing.assert_allclose(np.c_[el, nl, ul], np.c_[ea, na, ua], rtol=0, atol=0)


# --------------------------------------------------------------------- eq. (1) vs exact


def _discrepancy(origin, e: float, n: float, u: float = 0.0) -> tuple[float, tuple]:
    """|tangent - exact| in metres at the exact-ENU point (e, n, u), and the tangent vector."""
    lat, lon, h = ExactENU(*origin).to_geodetic(e, n, u)
    t = TangentPlaneENU(*origin).to_enu(lat, lon, h)
    return math.dist(t, (e, n, u)), t


def test_tangent_vs_exact_at_paper_latitude_300m() -> None:
    """The discrepancy of eq. (1) at 300 m is a scale error of the sphere R = a, not 5 cm.

    At 36.7 deg the meridian radius is M = 6358.2 km, so eq. (1)'s north axis is stretched
    by R/M - 1 = +0.313 %, its east axis shrunk by R/N - 1 = -0.120 %; the earth's
    curvature adds d^2/(2R) = 7 mm of height at 300 m.
    """
    M, N = _radii(PAPER_ORIGIN[0])
    d_n, (x, y, z) = _discrepancy(PAPER_ORIGIN, 0.0, 300.0)
    assert 0.933 < d_n < 0.935  # measured 0.9338 m
    assert y - 300.0 == pytest.approx(300.0 * (EARTH_RADIUS_M / M - 1.0), rel=0.02)
    assert abs(x) < 1e-9
    assert z == pytest.approx(300.0**2 / (2 * EARTH_RADIUS_M), abs=1e-4)  # 7.06 mm
    d_e, (x, y, z) = _discrepancy(PAPER_ORIGIN, 300.0, 0.0)
    assert 0.363 < d_e < 0.365  # measured 0.3639 m
    assert x - 300.0 == pytest.approx(300.0 * (EARTH_RADIUS_M / N - 1.0), rel=0.02)
    d_ne, _ = _discrepancy(PAPER_ORIGIN, 300.0 / math.sqrt(2), 300.0 / math.sqrt(2))
    assert 0.704 < d_ne < 0.707  # measured 0.7053 m
    # relative to the distance: at most 0.312 % at the paper's latitude
    for ang in np.linspace(0.0, 2 * math.pi, 24, endpoint=False):
        d, _ = _discrepancy(PAPER_ORIGIN, 300 * math.cos(ang), 300 * math.sin(ang), 20.0)
        assert d / 300.0 < 0.00312


@settings(max_examples=150, deadline=None)
@given(
    lat0=st.floats(min_value=-80.0, max_value=80.0),
    lon0=st.floats(min_value=-180.0, max_value=180.0),
    dist=st.floats(min_value=1.0, max_value=500.0),
    ang=st.floats(min_value=0.0, max_value=2 * math.pi),
    up=st.floats(min_value=-100.0, max_value=100.0),
)
def test_tangent_vs_exact_within_500m(lat0, lon0, dist, ang, up) -> None:
    """Within 500 m eq. (1) agrees with exact ENU up to its scale error (worst at the equator,
    R/M - 1 = 0.674 %) plus the curvature drop d^2/(2R), and anywhere in longitude."""
    origin = (lat0, lon0, 50.0)
    M, N = _radii(lat0)
    e, n = dist * math.cos(ang), dist * math.sin(ang)
    d, (x, y, _) = _discrepancy(origin, e, n, up)
    predicted = math.hypot(e * (EARTH_RADIUS_M / N - 1.0), n * (EARTH_RADIUS_M / M - 1.0))
    assert d <= 0.00675 * dist + dist**2 / (2 * EARTH_RADIUS_M) + 1e-6
    # what is left beyond the scale error is second order: measured <= 4.2e-5 of the distance
    assert abs(math.hypot(x - e, y - n) - predicted) < 6e-5 * dist


def test_tangent_across_the_antimeridian() -> None:
    """A frame straddling +-180 deg: a point 0.002 deg east of the line is 0.003 deg away."""
    fr = TangentPlaneENU(-16.8, 179.999, 10.0)  # Taveuni, Fiji
    ex = ExactENU(-16.8, 179.999, 10.0)
    x, y, z = fr.to_enu(-16.8, -179.998, 10.0)
    assert x == pytest.approx(EARTH_RADIUS_M * math.radians(0.003) * math.cos(math.radians(16.8)))
    assert 319.704 < x < 319.706
    assert (y, z) == (0.0, 0.0)
    assert math.dist((x, y, z), ex.to_enu(-16.8, -179.998, 10.0)) < 0.01 * 320
    _, lon, _ = fr.to_geodetic(x, y, z)
    assert lon == pytest.approx(-179.998, abs=1e-9)
    xs, _, _ = fr.to_enu(np.array([-16.8, -16.8]), np.array([-179.998, 179.998]), np.zeros(2))
    west = -EARTH_RADIUS_M * math.radians(0.001) * math.cos(math.radians(16.8))
    np.testing.assert_allclose(xs, [x, west], rtol=0, atol=1e-6)
    _, lons, _ = fr.to_geodetic(xs, np.zeros(2), np.zeros(2))
    np.testing.assert_allclose(lons, [-179.998, 179.998], rtol=0, atol=1e-9)
    # and the frame is consistent with the exact one on both sides of the line
    for lon in (-179.998, 179.998, 179.9995, -179.9999):
        t = fr.to_enu(-16.801, lon, 12.0)
        assert math.dist(t, ex.to_enu(-16.801, lon, 12.0)) < 0.00675 * math.hypot(*t[:2])


def test_exact_enu_array_path_is_pymap3d_bit_for_bit():
    """ExactENU.to_geodetic on float arrays skips pymap3d's per-call costs but does its
    operations in its order: the same bits (the simulator's logs depend on them)."""
    import pymap3d

    from estimator.geodesy import ExactENU

    rng = np.random.default_rng(7)
    for lat0, lon0, h0 in ((36.715, -4.478, 140.0), (-33.86, 151.21, 3.0), (64.1, -21.9, 60.0)):
        f = ExactENU(lat0, lon0, h0)
        for n in (1, 7, 300):
            e, no, u = (rng.uniform(-3000, 3000, n), rng.uniform(-3000, 3000, n),
                        rng.uniform(-200, 800, n))
            got = f.to_geodetic(e, no, u)
            want = pymap3d.enu2geodetic(e, no, u, lat0, lon0, h0)
            for g, w in zip(got, want, strict=True):
                assert np.array_equal(g, w)
        assert f.to_geodetic(10.0, 20.0, 5.0) == tuple(
            float(v) for v in pymap3d.enu2geodetic(10.0, 20.0, 5.0, lat0, lon0, h0))
