"""argparse value types shared by the ``osa`` subcommands: a bad value is a usage
error (exit 2, one line), never a traceback or a NaN carried into the work."""

from __future__ import annotations

import argparse
import math


def finite_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"not a finite number: {text!r}")
    return v


def positive_float(text: str) -> float:
    v = finite_float(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0: {text!r}")
    return v


def non_negative_float(text: str) -> float:
    v = finite_float(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0: {text!r}")
    return v


def float_in(lo: float, hi: float):
    """An argparse type: a finite number in [lo, hi]."""
    def parse(text: str) -> float:
        v = finite_float(text)
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"must be in [{lo:g}, {hi:g}]: {text!r}")
        return v

    return parse


def positive_int(text: str) -> int:
    v = non_negative_int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1: {text!r}")
    return v


def non_negative_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0: {text!r}")
    return v


def seed_arg(text: str, bits: int | None = None) -> int:
    """A seed (:func:`envs.seeds.check_seed`): a world seed, 0 .. 2^63 - 1, unless
    ``bits`` says otherwise."""
    from envs.seeds import WORLD_SEED_BITS, check_seed

    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    try:
        return check_seed(v, WORLD_SEED_BITS if bits is None else bits)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def train_seed_arg(text: str) -> int:
    """The seed of a training (an integer 0 .. 2^32 - 1: :data:`envs.seeds.TRAIN_SEED_BITS`)."""
    from envs.seeds import TRAIN_SEED_BITS

    return seed_arg(text, TRAIN_SEED_BITS)
