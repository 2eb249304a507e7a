"""The estimator's modes by name: the one place where a name becomes a :class:`ModeSpec`.

The paper's six (sec. Measurement-Noise Configurations) and ours, each a composition of
component objects (:class:`estimator.pipeline.ModeSpec`). The command line and the
options objects (:class:`estimator.online.EstimatorOptions`,
:class:`estimator.replay.ReplayOptions`) resolve names here, once; inside, a mode is
its spec. A mode composed in code (``ModeSpec("mine", noise=Nlos(), smoother=Ema())``)
needs no name here: pass the spec.
"""

from __future__ import annotations

from collections.abc import Iterable

from estimator.bootstrap import Robust
from estimator.filters import Ukf
from estimator.noise import Adaptive, Empirical, EmpiricalNlos, GnssInflated, Nlos
from estimator.pipeline import ModeSpec
from estimator.refined import REFINED
from estimator.smoothing import Ema

MODES: dict[str, ModeSpec] = {
    # the paper's six: an IEKF, constant R, the median smoother and the Gauss-Newton
    # bootstrap (baseline), each other mode changing one component
    "baseline": ModeSpec("baseline"),
    "nlos": ModeSpec("nlos", noise=Nlos()),  # R x 9 on NLoS, eq. (22)
    "empirical-r": ModeSpec("empirical-r", noise=Empirical()),  # eq. (23)
    "ukf": ModeSpec("ukf", filter=Ukf()),  # UKF3D, no bias state
    "ema": ModeSpec("ema", smoother=Ema()),  # EMA output smoothing
    "adaptive-r": ModeSpec("adaptive-r", noise=Adaptive()),  # eq. (24)
    # ours (sec. Conclusions' recommendations): damped robust bootstrap, honest
    # covariance with GNSS anchor uncertainty, NLoS-aware Empirical-R weighting
    "robust": ModeSpec("robust", noise=GnssInflated(EmpiricalNlos()), bootstrap=Robust(),
                       paper=False),
    # ours (issue 8): a static IEKF front refined by a robust batch (estimator.refined)
    "refined": REFINED,
}
PAPER_MODES: tuple[str, ...] = tuple(k for k, v in MODES.items() if v.paper)
# names that stand for a mode; estimates always carry the real name
MODE_ALIASES: dict[str, str] = {"best": "refined"}


def mode_name(name: str) -> str:
    """The real name of a mode or alias (``best`` -> ``refined``); ValueError if unknown."""
    real = MODE_ALIASES.get(name, name)
    if real not in MODES:
        raise ValueError(f"unknown mode {name!r}; choose from {', '.join([*MODES, *MODE_ALIASES])}")
    return real


def resolve_mode(mode: str | ModeSpec) -> ModeSpec:
    """The spec of a mode name or alias (a spec is returned as it is)."""
    if isinstance(mode, ModeSpec):
        return mode
    return MODES[mode_name(mode)]


def resolve_modes(modes: Iterable[str | ModeSpec]) -> tuple[ModeSpec, ...]:
    """Specs of names (aliases resolved) or specs; repeats of a name dropped (first kept,
    order preserved)."""
    out: list[ModeSpec] = []
    for m in modes:
        spec = resolve_mode(m)
        if all(o.name != spec.name for o in out):
            out.append(spec)
    return tuple(out)


def parse_modes(text: str) -> tuple[str, ...]:
    """The command line's ``--mode``: ``all`` (the paper's six), one name, or a list
    joined by ``,`` or ``+`` (``all+robust``: the six and ours); ``all`` expands in
    place, repeats are dropped. Returns the real names (``best`` -> ``refined``, the
    recommended mode), so the estimates carry them; :func:`resolve_modes` gives the specs.
    """
    names = [m.strip() for m in text.replace("+", ",").split(",") if m.strip()]
    expanded: list[str] = []
    for m in names:
        expanded.extend(PAPER_MODES if m == "all" else (m,))
    try:
        modes = tuple(s.name for s in resolve_modes(expanded))
    except ValueError:
        modes = ()
    if not modes:
        choices = ", ".join([*MODES, *MODE_ALIASES])
        raise ValueError(f"unknown mode {text!r}; choose from {choices} or all")
    return modes
