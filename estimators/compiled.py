"""How the estimators' per-pixel and per-point kernels are compiled: numba, cached on disk
(``estimators.warmup`` fills the cache), with NumPy's semantics for division — a zero divisor
gives inf or NaN, as the NumPy code each kernel replaced did, where numba's default raises
``ZeroDivisionError``. An exception in a vision worker is an estimator fault, and the
supervisor stops the approach on one; a non-finite value is what the NumPy-era code handles
(a feature dropped, a measurement lost)."""

from __future__ import annotations

import numba

#: ``@compiled``: a kernel.
compiled = numba.njit(cache=True, error_model="numpy")
#: ``@compiled_inline``: a small kernel compiled into each caller.
compiled_inline = numba.njit(cache=True, inline="always", error_model="numpy")
