"""Files as every layer writes them: a name as callers hold it, and a file written whole or not at
all (a temporary name renamed into place)."""

from __future__ import annotations

import os
from pathlib import Path

#: A file or folder name as callers hold it.
PathName = str | os.PathLike[str]


def write_atomic(path: PathName, data: str | bytes) -> None:
    """Write ``data`` (str or bytes) to ``path`` via a temporary file and an atomic rename."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.partial")
    mode = "wb" if isinstance(data, bytes) else "w"
    with open(temporary, mode, encoding=None if mode == "wb" else "utf-8") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)
