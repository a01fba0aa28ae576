"""Sub-commands of the `flockcal` command line, one module per group of commands.

Each module exposes `register(subparsers)`, which adds its sub-parsers and sets `func` on each;
heavy imports stay inside the functions so `flockcal --help` is fast.
"""
