"""The ``pfnet`` subcommands: each module exposes ``HELP``, ``add_arguments`` and ``run``
(see :mod:`pfnet.cli`); the work lives in the library modules they call."""
