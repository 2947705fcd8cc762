"""sisfilt: estimation for chains of interconnected subsystems whose sensors drop measurements
at random, from numpy arrays.

The same library as the ``sisfilt`` command line: a :class:`Model` from a TOML config (or a
changed copy, ``model.with_(p=0.7)``), :func:`simulate`, :func:`estimate` with every filter,
update and smoother of ``sisfilt estimate``, a step-by-step :class:`Filter` for live data, and
:func:`fit` of ``p``, ``Q`` and ``M`` by
maximum likelihood, and the Monte Carlo comparison :func:`evaluate`, in shards for a cluster with
:func:`evaluate_merge`. Arrays are float64 ``[T, N, ·]``: time step, subsystem, element; ``NaN``
in ``y`` marks a value that is not in the data. Bad input raises ``ValueError``, a numerical
breakdown ``ArithmeticError``.
"""

from ._sisfilt import (
    Estimates,
    Filter,
    Model,
    __version__,
    estimate,
    evaluate,
    evaluate_merge,
    fit,
    simulate,
)

__all__ = [
    "Estimates",
    "Filter",
    "Model",
    "estimate",
    "evaluate",
    "evaluate_merge",
    "fit",
    "simulate",
    "__version__",
]
