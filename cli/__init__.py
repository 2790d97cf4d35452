"""gravcal.cli: the ``gravcal`` command line, one module per subcommand (``cmd_NAME``)."""
