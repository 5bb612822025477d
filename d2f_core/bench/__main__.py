"""``python -m d2f_core.bench`` runs the ``d2f-bench`` CLI."""

from .render import main

raise SystemExit(main())
