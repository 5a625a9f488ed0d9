"""``python -m organlab.synthetic OUT``: write a synthetic session."""

from ._cli import main

raise SystemExit(main())
