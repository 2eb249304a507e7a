"""Fixtures of the import tests: the short simulated flight (tests/estimator/importers/
flights.py), simulated once per session (about 1 s), and its replayed estimates."""

from __future__ import annotations

import pytest

from tests.estimator.importers.flights import estimates, simulate_short
from tests.estimator.importers.writers import Flight


@pytest.fixture(scope="session")
def sim_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("sim") / "short.jsonl"
    simulate_short(path)
    return path


@pytest.fixture(scope="session")
def flight(sim_log) -> Flight:
    from tests.estimator.importers.writers import flight_from_log

    return flight_from_log(sim_log)


@pytest.fixture(scope="session")
def reference(sim_log) -> dict:
    return estimates(sim_log)
