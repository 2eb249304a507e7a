"""Seed sets: which world seeds train, validate and test policies (never mixed).

A world seed fixes a scenario's world (responders drawn in the area, sensor noise):
``sim.realise(scenario, seed)``. Training, validation during training, and the final
comparison of policies use disjoint ranges, so a trained policy is never scored on a
world it trained on:

==========  ======================  ==============================================
split       seeds                   used by
==========  ======================  ==============================================
train       0 ... 999 999           ``osa train`` episodes (drawn from the env's
                                    ``np_random`` within this range)
validation  1 000 000 ... 1 000 999 ``osa train`` evaluation during training
test        2 000 000 ... 2 000 999 ``osa evaluate --split test``, the
                                    benchmarks comparing policies
==========  ======================  ==============================================

A world seed is an integer from 0 to :data:`MAX_SEED` = 2^63 - 1, for every command
(``--seed``, ``--first-seed``: :func:`check_seed`): numpy's ``SeedSequence`` takes any
integer >= 0, and ``osa evaluate`` keeps seeds in int64 columns. The seed of a training
(``osa train --seed``, a sweep task's ``seed``) also seeds torch and NumPy's global
generator, which take 0 .. 2^32 - 1 (``check_seed(seed, TRAIN_SEED_BITS)``).

Without ``--split``, ``osa evaluate`` takes seeds K, K+1, ... from ``--first-seed K``
(default 0, the command-line contract's default and the numbers ``osa search --seed``
takes: for reproducing one world, or for the presets' own examples, which use small
seeds); comparisons that a trained policy enters belong on ``--split test``.
"""

from __future__ import annotations

WORLD_SEED_BITS = 63  # osa evaluate keeps seeds in int64 columns
MAX_SEED = 2**WORLD_SEED_BITS - 1  # a world seed is an integer 0 .. MAX_SEED (docs/cli.md)
TRAIN_SEED_BITS = 32  # osa train's seed: torch's and NumPy's global seeding take 0 .. 2^32 - 1

SPLITS: dict[str, tuple[int, int]] = {
    "train": (0, 1_000_000),
    "validation": (1_000_000, 1_001_000),
    "test": (2_000_000, 2_001_000),
}


def split_seeds(split: str, n: int, offset: int = 0) -> list[int]:
    """The first ``n`` seeds of a split (after ``offset``); raises past its end."""
    try:
        lo, hi = SPLITS[split]
    except KeyError:
        raise ValueError(f"unknown seed split {split!r}; choose from {', '.join(SPLITS)}") from None
    if n < 0 or offset < 0 or lo + offset + n > hi:
        raise ValueError(f"the {split} split holds seeds {lo}..{hi - 1}: cannot take {n} "
                         f"from offset {offset}")
    return list(range(lo + offset, lo + offset + n))


def split_of(seed: int) -> str | None:
    """The split a seed belongs to (None outside every split)."""
    for name, (lo, hi) in SPLITS.items():
        if lo <= seed < hi:
            return name
    return None


def check_seed(seed: int, bits: int = WORLD_SEED_BITS) -> int:
    """``seed`` if it is a seed (an int 0 .. 2^bits - 1: a world seed by default, up to
    :data:`MAX_SEED`), else ValueError with a one-line reason."""
    largest = 2**bits - 1
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ValueError(f"a seed is an integer, not {seed!r}")
    if not 0 <= seed <= largest:
        raise ValueError(f"a seed is an integer from 0 to 2^{bits} - 1 ({largest}), not {seed}")
    return seed
