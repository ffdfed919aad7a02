"""``python -m bench``: see :mod:`bench`."""

from bench import main

raise SystemExit(main())
