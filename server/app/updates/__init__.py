"""Learner updates, off the request path.

``manager`` (the ``UpdateManager``: the queue, its order and the database work), ``pool`` (the
local update processes), ``cluster`` (a Dask cluster instead), ``worker`` (what runs inside an
update process), ``warmup`` (compiling the kernels before the first update) and ``policies``
(the greedy policies the agents act by, cached).
"""
