"""``python -m sitl``: same as the ``sitl`` command."""

import sys

from sitl.cli import main

sys.exit(main())
