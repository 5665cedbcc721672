"""Allows ``python -m nplps``: runs the command line (see :mod:`nplps.cli`)."""

from .cli import main

raise SystemExit(main())
