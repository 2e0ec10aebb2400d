"""One module per ``illuminet`` subcommand; each defines ``register(subparsers)`` (see ``illuminet.cli``)."""
