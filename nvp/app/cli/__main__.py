"""``python -m nvp.app.cli`` (and ``torchrun -m nvp.app.cli``): the nvp command line."""

from nvp.app.cli import main

raise SystemExit(main())
