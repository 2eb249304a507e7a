"""Shared test settings.

Hypothesis explores new random examples on a developer's machine; under CI (``CI`` set)
it is derandomized so a submission's result does not depend on the draw.
"""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True, print_blob=True)
settings.register_profile("dev", print_blob=True)
settings.load_profile("ci" if os.environ.get("CI") else "dev")
