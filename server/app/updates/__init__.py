"""Learner updates, off the request path.

``manager`` (the ``UpdateManager``: puts the parts together, dispatches, says the capacity),
``queue`` (the order of the sessions' updates and the waits for them), ``store`` (the database
work), ``runners`` (where updates run: ``pool``, the local update processes, or ``cluster``, a
Dask cluster), ``worker`` (what runs inside an update process), ``warmup`` (compiling the
kernels before the first update), ``capacity`` (participants who can teach at once) and
``policies`` (the greedy policies the agents act by, cached).
"""
