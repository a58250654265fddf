"""``python -m phjax``: the command-line interface (see ``phjax --help``)."""

from .cli import main

raise SystemExit(main())
