"""Subcommands of ``python -m hil``: one module each, registered in ``hil.__main__``.

A subcommand module defines ``HELP`` (one line), ``add_arguments(parser)`` and
``main(args) -> int`` (the exit status).
"""
