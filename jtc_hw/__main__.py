"""``python -m jtc_hw`` is ``jtc-hw``."""

from .cli import main

raise SystemExit(main())
