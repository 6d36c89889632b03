"""The ``pfnet`` subcommands, one module each (registered in :data:`pfnet.cli.COMMANDS`).

A command module holds only ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``,
and small private helpers that turn options into library calls: it parses, checks the
options (naming them, e.g. ``--batch-size``), calls the library and prints. The work lives
in library modules that know nothing of argparse and raise :class:`pfnet.errors.PfnetError`
subclasses that speak of their parameters, never of flags. Commands never import one
another; what two commands share belongs in the library.
"""
