"""Where the simulator, the estimator and the planner meet: the closed loop, the
Gymnasium and PettingZoo environments, policies by name, evaluation and the CLI.

``import envs`` registers the Gymnasium environments (``osa/Search-v0``,
``osa/Waypoint-v0``; :mod:`envs.gym.registration`): at once when Gymnasium is already
imported, else as soon as it is (so ``osa --help`` does not pay for importing it).
"""

from __future__ import annotations

import importlib.abc
import importlib.util
import sys


def _register() -> None:
    from envs.gym.registration import register_envs

    register_envs()


class _RegisterAfterGymnasium(importlib.abc.MetaPathFinder):
    """Registers the environments right after ``gymnasium`` has been imported."""

    def find_spec(self, name, path=None, target=None):
        if name != "gymnasium":
            return None
        if self in sys.meta_path:
            sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            return spec
        exec_module = spec.loader.exec_module

        def exec_then_register(module) -> None:
            exec_module(module)
            _register()

        spec.loader.exec_module = exec_then_register  # this spec's loader object only
        return spec


if "gymnasium" in sys.modules:
    _register()
elif not any(isinstance(f, _RegisterAfterGymnasium) for f in sys.meta_path):
    sys.meta_path.insert(0, _RegisterAfterGymnasium())
