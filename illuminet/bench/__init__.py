"""One module per ``illuminet bench NAME``; each defines ``run(args, cfg) -> dict`` (see
``illuminet.commands.bench``)."""
