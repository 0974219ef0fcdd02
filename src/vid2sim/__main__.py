"""``python -m vid2sim`` runs the ``vid2sim`` command."""

import sys

from vid2sim.cli import main

sys.exit(main())
