"""BAM Study analysis: a study's data to the paper's results tables, tests and plots."""
