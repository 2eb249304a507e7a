"""The range measurement model, written once: h(p, u, b) = |p - u| + b (eqs. 2, 13, 14).

p is the responder (the unknown AP) and u the initiator's GNSS antenna (the virtual
anchor), both ENU metres; b is the residual FTM range bias. The Jacobian of h with
respect to (p, b) is the row [(p - u) / |p - u|, 1] (eq. 14); with respect to u it is
the negative of the position part. Everything that predicts a range or linearises one
calls this module: the filters (:mod:`estimator.filters`, scalar form), the bootstrap
and the batch refinement (NumPy form), the planner's geometry scores, its CasADi
information objective and the adaptive policy's coarse fit.

**The near-zero rule** (one for every form): the geometric range is

    r = sqrt(max(|p - u|^2, RANGE_FLOOR_M^2)),   RANGE_FLOOR_M = 1 nm,

and the Jacobian's position part is its derivative: (p - u) / r, and zero where the
floor holds. Away from the anchor (|p - u| > 1 nm, i.e. always in practice: the drone
flies tens of metres from any estimate) this is exactly sqrt(dx^2 + dy^2 + dz^2) and
(p - u) / r, bit for bit. When the anchor sits on the estimate (|p - u| <= 1 nm) the
predicted range is 1 nm (+ b) and the position part of the Jacobian is the zero
vector: such a range says nothing about the direction of the responder, only about
the bias, so a filter update moves the bias alone and the position rows of a normal
matrix or a Fisher information get nothing from it. Nothing divides by zero, nothing
becomes NaN, and the CasADi form is the same function (the floor applied to |p - u|^2,
under the square root), so its derivatives are finite and the same. 1 nm is far below
anything the radio resolves (centimetres) and far above the underflow of its square
(1e-18 m^2).

Three forms of the same arithmetic: NumPy (vectorised over anchors, broadcasting),
scalar (plain floats, for the unrolled filter updates) and CasADi (symbolic). The
NumPy and scalar forms give the same bits: the squared norm is dx*dx + dy*dy + dz*dz
summed left to right in both (tests/estimator/test_measurement.py).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

RANGE_FLOOR_M = 1e-9  # the near-zero rule's floor on |p - u| (module docstring)
RANGE_FLOOR2_M2 = RANGE_FLOOR_M * RANGE_FLOOR_M
_R_MIN = math.sqrt(RANGE_FLOOR2_M2)  # the range where the floor holds (1 nm, as rounded)

# ----------------------------------------------------------------------------- NumPy


def range_of_difference(diff_m: ArrayLike) -> np.ndarray:
    """|p - u| under the near-zero rule, of the differences p - u (last axis E, N, U)."""
    diff = np.asarray(diff_m, dtype=float)
    return np.sqrt(np.maximum((diff * diff).sum(axis=-1), RANGE_FLOOR2_M2))


def geometric_range_m(p_enu_m: ArrayLike, u_enu_m: ArrayLike) -> np.ndarray:
    """|p - u| under the near-zero rule; ``p`` and ``u`` broadcast over leading axes
    (the last axis holds E, N, U)."""
    return range_of_difference(np.asarray(p_enu_m, dtype=float) - np.asarray(u_enu_m, dtype=float))


def predicted_range_m(p_enu_m: ArrayLike, u_enu_m: ArrayLike, bias_m: ArrayLike = 0.0
                      ) -> np.ndarray:
    """h(p, u, b) = |p - u| + b (eq. 13), vectorised like :func:`geometric_range_m`."""
    return geometric_range_m(p_enu_m, u_enu_m) + bias_m


def jacobian_rows(diff_m: np.ndarray, r_m: np.ndarray, *, scale: ArrayLike | None = None,
                  bias: bool = False) -> np.ndarray:
    """Rows of dh/dp = (p - u) / r (eq. 14; zero where the floor holds) from the
    differences and their ranges (:func:`range_of_difference`).

    ``scale`` (one weight per row, e.g. 1 / sigma) gives the whitened rows
    (p - u) * (scale / r) (and ``scale`` in the bias column), the product taken in that
    order; ``bias`` appends dh/db = 1 (times ``scale``) as a fourth column.
    """
    if scale is None:
        J = diff_m / r_m[..., None]
    else:
        scale = np.asarray(scale, dtype=float)
        J = diff_m * (scale / r_m)[..., None]
    if r_m.size and r_m.min() <= _R_MIN:  # on the anchor: no direction
        J[r_m <= _R_MIN] = 0.0
    if bias:
        last = np.ones(r_m.shape) if scale is None else np.broadcast_to(scale, r_m.shape)
        J = np.concatenate([J, last[..., None]], axis=-1)
    return J


def range_jacobian(p_enu_m: ArrayLike, u_enu_m: ArrayLike, *, bias: bool = False,
                   scale: ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(r, J): the geometric range and :func:`jacobian_rows` at p for anchors u."""
    diff = np.asarray(p_enu_m, dtype=float) - np.asarray(u_enu_m, dtype=float)
    r = range_of_difference(diff)
    return r, jacobian_rows(diff, r, scale=scale, bias=bias)


# ----------------------------------------------------------------------------- scalar


def range_of(dx: float, dy: float, dz: float) -> float:
    """The geometric range of the difference (dx, dy, dz) = p - u (plain floats)."""
    d2 = dx * dx + dy * dy + dz * dz
    if d2 < RANGE_FLOOR2_M2:
        d2 = RANGE_FLOOR2_M2
    return math.sqrt(d2)


def range_and_unit(dx: float, dy: float, dz: float) -> tuple[float, float, float, float]:
    """(r, dx / r, dy / r, dz / r): the range and the position part of eq. (14)'s
    Jacobian row for the difference p - u (plain floats; the bias part is 1; zero where
    the floor holds)."""
    d2 = dx * dx + dy * dy + dz * dz
    if d2 < RANGE_FLOOR2_M2:
        d2 = RANGE_FLOOR2_M2
    r = math.sqrt(d2)
    if r <= _R_MIN:  # on the anchor: no direction
        return r, 0.0, 0.0, 0.0
    return r, dx / r, dy / r, dz / r


# ----------------------------------------------------------------------------- CasADi


def range_casadi(diff):
    """(r^2, r) of a CasADi 3 x N difference p - u, column by column, under the
    near-zero rule (floored before the square root, so derivatives stay finite)."""
    import casadi as ca

    d2 = ca.fmax(ca.sum1(diff * diff), RANGE_FLOOR2_M2)
    return d2, ca.sqrt(d2)
