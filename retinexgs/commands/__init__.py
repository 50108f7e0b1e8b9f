"""The command line's sub-commands, one module per stage: each ``register(subparsers)`` adds its
sub-command(s). They assemble the library's layers (train, the viewer, export...), so they stand above them all;
each imports the heavy parts inside the function that runs the command, to keep ``retinexgs --help`` fast."""
