"""``python -m miem``: the ``miem`` command line (see :mod:`miem.cli`)."""

from .cli import main

raise SystemExit(main())
