"""``python -m mission_runner.cli``: as ``mission-runner``."""

import sys

from . import main

sys.exit(main())
