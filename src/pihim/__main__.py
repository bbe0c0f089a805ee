"""``python -m pihim`` runs the command line."""

import sys

from pihim.cli import main

sys.exit(main())
