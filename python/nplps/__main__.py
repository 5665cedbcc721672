"""Entry point of ``python -m nplps``: run the command line (see :mod:`nplps.cli`)."""

from .cli import main

raise SystemExit(main())
