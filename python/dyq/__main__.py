"""``python -m dyq``: the ``dyq`` command."""
import sys

from .apps.cli import main

sys.exit(main())
