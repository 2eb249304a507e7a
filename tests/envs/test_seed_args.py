"""One definition of a world seed for every command (envs/seeds.py, docs/cli.md
Conventions): an integer 0 .. 2^63 - 1; anything else one line and exit status 2.
``osa search`` took seeds past 2^63 that ``osa evaluate`` refused."""

from __future__ import annotations

import numpy as np
import pytest

from envs.cli import build_parser, join_negative_values
from envs.commands.evaluate import seeds_of
from envs.seeds import MAX_SEED, check_seed
from sim.realisation import realise
from sim.scenario import load_scenario
from tests.cli import one_line, status_of

SCENARIO = "search-random-los-rtk"
HUGE = 2**64 + 3


def _argv(command: str, seed: str, out) -> list[str]:
    if command == "search":
        return ["search", SCENARIO, "--seed", seed, "-o", str(out), "--no-progress"]
    return ["evaluate", SCENARIO, "--policies", "lawnmower", "--seeds", "1",
            "--first-seed", seed, "-o", str(out / "rows.csv"), "--workers", "1"]


@pytest.mark.parametrize("command", ["search", "evaluate"])
@pytest.mark.parametrize(("seed", "reason"), [
    (str(HUGE), f"a seed is an integer from 0 to 2^63 - 1 ({MAX_SEED}), not {HUGE}"),
    ("-1", f"a seed is an integer from 0 to 2^63 - 1 ({MAX_SEED}), not -1"),
    ("abc", "not an integer: 'abc'"),
])
def test_a_bad_seed_is_one_line_and_status_2_for_both(command, seed, reason, capsys, tmp_path):
    out = tmp_path / "out"
    assert status_of(_argv(command, seed, out)) == 2
    option = "--seed" if command == "search" else "--first-seed"
    assert one_line(capsys) == f"osa: error: argument {option}: {reason}"
    assert not out.exists()  # refused before any work


@pytest.mark.parametrize("command", ["search", "evaluate"])
def test_the_largest_seed_is_taken_by_both(command, tmp_path):
    parser = build_parser()
    args = parser.parse_args(join_negative_values(parser, _argv(command, str(MAX_SEED),
                                                                 tmp_path)))
    assert (args.seed if command == "search" else args.first_seed) == MAX_SEED


def test_check_seed_bounds_and_the_world_of_the_largest():
    assert MAX_SEED == 9223372036854775807
    assert check_seed(0) == 0 and check_seed(MAX_SEED) == MAX_SEED
    for bad in (-1, MAX_SEED + 1, HUGE, True, 1.0, "3"):
        with pytest.raises(ValueError, match="a seed is an integer"):
            check_seed(bad)
    # the same ranges osa evaluate flies: the last seed may be MAX_SEED, not past it
    assert seeds_of(1, MAX_SEED, None) == [MAX_SEED]
    assert seeds_of(2, MAX_SEED - 1, None) == [MAX_SEED - 1, MAX_SEED]
    with pytest.raises(ValueError, match="pass the largest seed"):
        seeds_of(2, MAX_SEED, None)
    sc = load_scenario(SCENARIO)  # the largest seed draws a world, another than seed 0's
    far, zero = realise(sc, MAX_SEED).world, realise(sc, 0).world
    assert len(far.responders) == len(zero.responders) >= 1
    assert np.abs(far.responder_enu_m() - zero.responder_enu_m()).max() > 1.0


@pytest.mark.parametrize("seed", [str(2**32), "-1"])
def test_a_training_seed_past_2_32_is_one_line_not_an_internal_error(seed, capsys, tmp_path):
    """Before: ``osa train --seed 2^40`` was an internal error (torch's and NumPy's
    global seeding take 0 .. 2^32 - 1)."""
    out = tmp_path / "model"
    assert status_of(["train", "--seed", seed, "--steps", "8", "-o", str(out)]) == 2
    assert one_line(capsys) == (f"osa: error: argument --seed: a seed is an integer from 0 "
                                f"to 2^32 - 1 (4294967295), not {seed}")
    assert not out.exists()


def test_a_sweep_task_seed_past_2_32_is_refused(tmp_path):
    from envs.sweep import SweepError, read_sweep

    p = tmp_path / "sweep.toml"
    p.write_text(f'steps = 8\n[[task]]\nname = "a"\nseed = {2**32}\n')
    with pytest.raises(SweepError, match=r"seed: a seed is an integer from 0 to 2\^32 - 1"):
        read_sweep(p, {})
    p.write_text(f'steps = 8\n[[task]]\nname = "a"\nseed = {2**32 - 1}\n')
    assert read_sweep(p, {})[0]["seed"] == 2**32 - 1
