"""What an install does before a benchmark's processes start: compile the packages to bytecode, so
that each process reads it instead of compiling its sources (seconds of CPU that no installed
runner spends), even where ``PYTHONDONTWRITEBYTECODE`` is set."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


def compile_packages(root: Path) -> None:
    """Byte-compile ``mission_runner`` and ``sitl`` under ``root``."""
    packages = [str(root / "mission_runner"), str(root / "sitl")]
    subprocess.run(
        [sys.executable, "-m", "compileall", "-q", *packages],
        check=True,
        stdout=subprocess.DEVNULL,
        env={**os.environ, "PYTHONDONTWRITEBYTECODE": ""},
    )
