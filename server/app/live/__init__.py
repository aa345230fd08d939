"""Watching a study while it runs: the funnel of who is where (``funnel``), one participant's
current session as they see it (``mirror``), the agents' learning curves so far (``curves``),
each computed once per interval for every dashboard that watches (``broadcast``)."""
