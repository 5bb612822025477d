"""``python -m d2f_core.synth`` runs the ``d2f-synth`` CLI."""

from .dataset import main

raise SystemExit(main())
