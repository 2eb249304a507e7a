"""Scenario files at the edges of what the loader accepts (the seeds sweep): each is
flown or refused with one line naming the file and the key, never a traceback."""

from __future__ import annotations

import pytest

from sim.scenario import ScenarioError, load_scenario, min_search_height_m

BASE = """
[world.origin]
lat_deg = 36.715
lon_deg = -4.478
h_m = 140.0

[search]
area_enu_m = [[-250.0, -250.0], [250.0, -250.0], [250.0, 250.0], [-250.0, 250.0]]
start_e_m = 0.0
start_n_m = -240.0
budget_s = 60.0
random_responders = 1
"""


def write(tmp_path, text: str, name: str = "edge.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize("text, message", [
    # the autopilot flies on its GNSS: 2.5 m sigma of vertical bias (standalone) cannot
    # hold 5 m above the ground (it flew 1.2 m into it on seed 0 of search-random-los)
    (BASE.replace("budget_s", "height_m = 5.0\nbudget_s"),
     "search.height_m: 5 m is below 10.0 m"),
    (BASE + "\n[randomise]\ngnss_bias_scale = [0.5, 20.0]\n",
     "search.height_m: 45 m is below 200.0 m"),
    (BASE.replace("start_e_m = 0.0\n", ""), "search: missing key 'start_e_m'"),
    (BASE.replace("budget_s", "budgett_s"), "search: unknown key 'budgett_s'"),
    (BASE + '\n[world.terrain]\nkind = "grid"\ne0_m = 0\nn0_m = 0\nspacing_m = 10\n'
            'heights_m = [[0.0, 1.0], [2.0]]\n',
     "world.terrain.heights_m: expected rows of numbers, all of the same length"),
    (BASE + '\n[[agents]]\nname = "a"\nspeed = 3.0\n',
     "agents[0]: unknown key 'speed' (known: gnss, kind, name, start_e_m, start_n_m, vehicle)"),
    (BASE + '\n[[agents]]\nname = "a"\n[[agents]]\nname = "b"\nstart_e_m = 30.0\n',
     "agents[1]: agent b: give both start_e_m and start_n_m, or neither"),
    (BASE + '\n[[agents]]\nname = "a"\n[[agents]]\nname = "b"\nstart_e_m = 3000.0\n'
            'start_n_m = -240.0\n',
     "agents[1]: b's start (3000, -240) is outside the search area"),
    (BASE + '\n[[search.keepout]]\ncircle_enu_m = [60.0, -240.0, 10.0]\n'
            '[[agents]]\nname = "a"\n[[agents]]\nname = "b"\nstart_e_m = 60.0\n'
            'start_n_m = -240.0\n',
     "agents[1]: b's start (60, -240) is inside keep-out keepout[0]"),
])

def test_a_bad_value_is_one_line_naming_the_file_and_the_key(tmp_path, text, message):
    p = write(tmp_path, text)
    with pytest.raises(ScenarioError) as exc:
        load_scenario(p)
    msg = str(exc.value)
    assert msg.startswith(f"{p}: ") and message in msg and "\n" not in msg, msg


GRID = '\n[world.terrain]\nkind = "grid"\ne0_m = -300\nn0_m = -300\nspacing_m = 300\n'
RESPONDER = '\n[[world.responders]]\nname = "x"\nbssid = "a4:77:33:0f:aa:01"\ne_m = 0\nn_m = 0\n'


# each was a traceback (TypeError, ValueError: "internal error" at the command line) or,
# for the huge values, a crash mid-search (a height or range of 1e300 overflowing)
@pytest.mark.parametrize("text, message", [
    ('gnss = "rtk"\n' + BASE, "gnss: expected a table, got str"),
    (BASE + '\n[gnss]\npreset = ["rtk"]\n', "gnss.preset: ['rtk'] is not one of standalone, rtk"),
    (BASE + '\n[[agents]]\nname = "a"\ngnss = 5\n', "agents[0].gnss: expected a table, got int"),
    (BASE + '\n[[agents]]\nname = "a"\ngnss = {preset = ["rtk"]}\n',
     "agents[0].gnss.preset: ['rtk'] is not one of standalone, rtk"),
    (BASE + '\n[world]\nterrain = "hills"\n', "world.terrain: expected a table, got str"),
    (BASE + '\n[flight]\nkind = ["pass"]\n',
     "flight.kind: ['pass'] is not one of sweeps, pass, waypoints"),
    (BASE + GRID + 'file = 5\n', "world.terrain.file: expected a file name"),
    (BASE + GRID + 'heights_m = [[1.0, 2.0], [true, 0.0]]\n',
     "world.terrain.heights_m: expected rows of numbers"),
    (BASE + GRID + 'heights_m = [[1.0, 2.0], [1e300, 0.0]]\n',
     "world.terrain.heights_m: terrain grid holds a height beyond 20000 m"),
    (BASE + GRID.replace("spacing_m = 300", "spacing_m = 1e300") + 'heights_m = [[1, 2], [3, 4]]\n',
     "spacing_m 1e+300 m is beyond 20000 m"),
    (BASE + GRID.replace("e0_m = -300", "e0_m = -1e300") + 'heights_m = [[1, 2], [3, 4]]\n',
     "e0_m -1e+300 m is beyond 20000 m"),
    (BASE + '\n[world.terrain]\nhills = [{e_m = 0, n_m = 0, height_m = 1e300, sigma_m = 10}]\n',
     "world.terrain.hills[0]: hill height_m 1e+300 m is beyond 20000 m"),
    (BASE + '\n[world.terrain]\nbase_m = -25000.0\n', "base_m -25000 m is beyond 20000 m"),
    (BASE + '\n[[search.keepout]]\npolygon_enu_m = [["a", "b"], [10, 0], [10, 10]]\n',
     "search.keepout[0].polygon_enu_m: expected an array of [e, n] pairs of numbers"),
    (BASE + '\n[[search.keepout]]\npolygon_enu_m = [[true, 0], [10, 0], [10, 10]]\n',
     "search.keepout[0].polygon_enu_m: expected an array of [e, n] pairs of numbers"),
    (BASE + RESPONDER + 'antenna_height_m = 1e300\n',
     "responder x antenna_height_m 1e+300 m is beyond 1000 m"),
    (BASE + RESPONDER + 'range_offset_m = 1e300\n',
     "responder x range_offset_m 1e+300 m is beyond 20000 m"),
    (BASE + '\n[ftm]\noffset_max_m = 1e300\n', "ftm: offset_max_m 1e+300 m is beyond 20000 m"),
    (BASE + '\n[[agents]]\nname = "a"\n[[agents]]\nname = "g"\nkind = "ground"\n'
            'vehicle = {ground_height_m = 1e300}\n',
     "agents[1].vehicle: ground_height_m 1e+300 m is beyond 1000 m"),
    # osa search writes agent NAME's log as flight-NAME.jsonl: a crash (FileNotFoundError)
    # after the whole search, or on a case-insensitive disk one log over another
    (BASE + '\n[[agents]]\nname = "a"\n[[agents]]\nname = "../b"\n',
     "agents[1].name: '../b' cannot be part of a file name"),
    (BASE + '\n[[agents]]\nname = "a\\u0007"\n', "agents[0].name: 'a\\x07' cannot be part of"),
    (BASE + '\n[[agents]]\nname = "uav"\n[[agents]]\nname = "UAV"\n',
     "agents[1].name: 'UAV' is used twice (letter case aside)"),
    (BASE + '\n[gnss]\nwhite_sigma_h_m = 1e300\n',
     "gnss: white_sigma_h_m 1e+300 m is beyond 20000 m"),
    (BASE + '\n[gnss]\nbias_sigma_h_m = 1e300\n',
     "gnss: bias_sigma_h_m 1e+300 m is beyond 20000 m"),
    # every DEM height NaN: "cannot convert float NaN to integer" (an internal error)
    ('extends = "site-valley"\n[world.terrain]\ndatum_offset_m = 1e300\n',
     "valley-dem.tif: datum_offset_m 1e+300 m is beyond 20000 m"),
    # a sigma^2 that underflows to 0: a ZeroDivisionError placing the responders
    (BASE + '\n[world.terrain]\nhills = [{e_m = 0, n_m = 0, height_m = 10, sigma_m = 1e-200}]\n',
     "world.terrain.hills[0]: hill sigma_m 1e-200 m is below 0.1 m"),
    # loaded, then world seed 3 drew 6.6 m/s and crashed (osa search, the envs' reset)
    (BASE + '\n[vehicle]\nmax_speed_mps = 6.0\n[randomise]\nwind_mps = [0.0, 10.0]\n',
     "randomise.wind_mps: up to 10 m/s, at or above vehicle max_speed_mps 6 m/s"),
    (BASE + '\n[randomise]\nwind_mps = [0.0, 2.0]\n[[agents]]\nname = "a"\n[[agents]]\n'
            'name = "g"\nkind = "ground"\n',
     "randomise.wind_mps: up to 2 m/s, at or above agent g's max_speed_mps 1.4 m/s"),
])
def test_a_mistyped_or_impossible_value_is_one_line_too(tmp_path, text, message):
    test_a_bad_value_is_one_line_naming_the_file_and_the_key(tmp_path, text, message)


def test_the_bounds_themselves_are_accepted(tmp_path):
    """The largest accepted values load (and keep their numbers)."""
    text = (BASE + GRID + 'heights_m = [[1.0, 2.0], [20000.0, 0.0]]\n' + RESPONDER
            + 'antenna_height_m = 1000.0\nrange_offset_m = -20000.0\n')
    sc = load_scenario(write(tmp_path, text))
    r = sc.world.responders[0]
    assert (r.antenna_height_m, r.range_offset_m) == (1000.0, -20000.0)
    # bilinear between (-300, -300) 1, (0, -300) 2, (-300, 0) 20000 and (0, 0) 0: the middle
    assert sc.world.ground_m(-150.0, -150.0) == pytest.approx((1 + 2 + 20000 + 0) / 4)


def test_an_unknown_search_key_lists_the_file_names_of_the_keys(tmp_path):
    with pytest.raises(ScenarioError) as exc:
        load_scenario(write(tmp_path, BASE.replace("budget_s", "budgett_s")))
    known = str(exc.value).split("(known: ")[1]
    assert "keepout," in known and "keepouts" not in known and "area_geo" in known


def test_the_search_height_floor_follows_the_vertical_gnss_error(tmp_path):
    rtk = load_scenario(write(tmp_path, BASE.replace("budget_s", "height_m = 3.0\nbudget_s")
                              + '\n[gnss]\npreset = "rtk"\n'))
    assert rtk.search.height_m == 3.0 and min_search_height_m(rtk) == 2.0
    sa = load_scenario(write(tmp_path, BASE, "sa.toml"))
    # 4 x hypot(2.5 m bias, 0.15 m wander)
    assert min_search_height_m(sa) == pytest.approx(4 * (2.5**2 + 0.15**2) ** 0.5, abs=1e-12)
    for name in ("search-random-los", "search-five-mixed", "site-valley",
                 "suite/r5-h30-sa-u4"):
        sc = load_scenario(name)
        assert sc.search.height_m >= min_search_height_m(sc), name


def test_a_variant_of_a_site_preset_finds_the_presets_files(tmp_path):
    """``extends = "site-valley"`` from another folder: the preset's DEM, area and
    keep-out files are the preset's (before: looked for beside the variant, exit 2)."""
    p = write(tmp_path, 'extends = "site-valley"\nname = "short"\n[search]\nbudget_s = 300.0\n')
    variant, preset = load_scenario(p), load_scenario("site-valley")
    assert variant.search.budget_s == 300.0
    assert variant.search.area_enu_m == preset.search.area_enu_m
    assert variant.keepouts == preset.keepouts and len(variant.keepouts) > 1
    e, n = 100.0, 50.0
    assert variant.world.ground_m(e, n) == preset.world.ground_m(e, n)


def test_a_file_saved_with_a_byte_order_mark_or_as_utf16(tmp_path):
    """Notepad's UTF-8 with a byte order mark loads as without (before: "invalid TOML:
    Invalid statement (at line 1, column 1)", nothing to see there); PowerShell's
    UTF-16 is one line saying so."""
    bom = tmp_path / "bom.toml"
    bom.write_bytes(b"\xef\xbb\xbf" + BASE.encode())
    assert load_scenario(bom).search == load_scenario(write(tmp_path, BASE)).search
    u16 = tmp_path / "u16.toml"
    u16.write_bytes(BASE.encode("utf-16"))
    with pytest.raises(ScenarioError) as exc:
        load_scenario(u16)
    assert str(exc.value) == (f"cannot read scenario file {u16}: a TOML file is UTF-8 text, "
                              "invalid start byte at byte 0 (it is UTF-16: save it as UTF-8)")


def test_a_folder_is_not_a_missing_file(tmp_path):
    """``osa search some/folder``: said to be a folder (before: "does not exist")."""
    with pytest.raises(ScenarioError, match=f"^scenario {tmp_path} is a folder, not a "
                                            "scenario file$"):
        load_scenario(tmp_path)


@pytest.mark.parametrize("parent, message", [
    ("nope", "extends: unknown scenario 'nope' (presets: "),
    ("suite/r5-c30-sa-u3", "extends: suite preset 'suite/r5-c30-sa-u3': UAVs u3 is not one "
                           "of 1, 2, 4"),
])
def test_a_bad_parent_names_the_file_that_extends_it(tmp_path, parent, message):
    """Before: only "unknown scenario 'nope' ...", not which file said so."""
    p = write(tmp_path, f'extends = "{parent}"\n')
    with pytest.raises(ScenarioError) as exc:
        load_scenario(p)
    assert str(exc.value).startswith(f"{p}: {message}") and "\n" not in str(exc.value)
