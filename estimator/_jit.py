"""Small loops compiled with numba on first use (numba is imported then, not with the
packages that use them).

The loops given to :func:`compiled` use only float arithmetic, comparisons, ``sqrt``,
``math.floor`` and ``np.hypot`` (libm's, compiled or not) and, where a result only
places a bound, libm's transcendental functions: run interpreted
(``NUMBA_DISABLE_JIT=1``) they give the same values.
"""

from __future__ import annotations

import functools
from collections.abc import Callable


@functools.cache
def compiled(f: Callable) -> Callable:
    """``f`` compiled (``numba.njit``, cached on disk) the first time it is asked for."""
    from numba import njit

    return njit(cache=True)(f)
