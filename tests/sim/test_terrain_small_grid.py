"""A grid terrain of fewer than 4 nodes an axis (the seeds sweep: a 3 x 3 grid made
CasADi's B-spline refuse, a traceback of ``osa search --policy adaptive``)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from sim.terrain import GridTerrain


@pytest.mark.parametrize("heights", [
    [[0.0, 10.0], [20.0, 30.0]],
    [[0.0, 0.0, 0.0], [0.0, 300.0, 0.0], [0.0, 0.0, 0.0]],
    [[0.0, 5.0, 1.0, 2.0], [3.0, 4.0, 8.0, 9.0]],
])
def test_the_casadi_surface_of_a_small_grid_goes_through_its_nodes(heights):
    g = GridTerrain(np.array(heights), -100.0, -50.0, 100.0)
    e, n = ca.MX.sym("e"), ca.MX.sym("n")
    f = ca.Function("h", [e, n], [g.height_m(e, n)])
    ny, nx = g.heights_m.shape
    for i in range(ny):
        for j in range(nx):
            ej, ni = -100.0 + 100.0 * j, -50.0 + 100.0 * i
            assert float(f(ej, ni)) == pytest.approx(heights[i][j], abs=1e-9)
    # the split cells' new nodes lie on the grid's own bilinear surface
    if nx == 2:
        assert float(f(-100.0 + 100.0 / 3, -50.0)) == pytest.approx(10.0 / 3, abs=1e-9)
