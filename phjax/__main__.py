"""``python -m phjax``: the command-line interface (see ``phjax --help``)."""

from .cli._main import main

raise SystemExit(main())
