"""The ``bam-study`` subcommands (``server.cli`` lists them), one module each."""
