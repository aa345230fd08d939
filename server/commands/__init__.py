"""``bam-study`` and its subcommands: ``main`` dispatches to ``serve``, ``db``, ``export``,
``demo``, ``teach``, ``simulate`` and ``analyze``; ``live`` and ``simulated`` are the live server
and the simulated participants that ``demo``, ``teach`` and the benchmarks drive."""
