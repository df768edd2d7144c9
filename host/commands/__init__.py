"""One module per ``stereopath`` subcommand: ``add_arguments(parser)`` and ``run(args) -> int``.

Command modules import only the standard library at module level, so that
``stereopath --help`` is instant and the device needs no host libraries.
"""
