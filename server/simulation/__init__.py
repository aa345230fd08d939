"""The paper's simulated-teacher experiments (section 4): ``bam-study simulate``.

An experiment teaches many independent agents (one per environment, learner and agent index)
with a simulated teacher for a number of rounds and scores each agent's policies after every
round. ``protocols`` is one agent's run, ``runner`` executes the jobs (in this process, a local
process pool or a Dask cluster) and resumes interrupted runs, ``outputs`` and ``plots`` write
the CSVs, the figure and the report, and ``cli`` is the command.

The package itself imports nothing, so that ``bam-study --help`` stays fast; import from the
modules (``from server.simulation.runner import run_jobs``).
"""
