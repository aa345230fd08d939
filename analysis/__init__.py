"""BAM Study analysis: a study's data to the paper's results tables, tests and plots.

``data`` reads and validates an export (``load_tables``); ``stats`` holds the per-session
measures and the statistical comparisons; ``results.analyze`` runs the whole analysis;
``tables`` and ``plots`` render it; ``report.write_outputs`` writes it all or nothing; ``cli``
is ``bam-study analyze``.
"""
