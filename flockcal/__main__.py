"""Lets `python -m flockcal` run the command line."""

from flockcal.cli import main

raise SystemExit(main())
