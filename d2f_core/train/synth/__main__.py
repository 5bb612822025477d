"""``python -m d2f_core.train.synth`` runs the ``d2f-synth`` CLI."""

from .dataset import main

raise SystemExit(main())
