"""Finding the data files that are not shipped with the package (the Happy Buddha mesh).

Data is looked up in the directory given by the caller (``data_dir=``, ``--data``), else in
the one named by the ``PARTPM_DATA`` environment variable; never at a hard-coded path.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

__all__ = ["DATA_ENV", "MissingDataError", "find_data_file", "DATA_FILES"]

#: Environment variable naming the data directory.
DATA_ENV = "PARTPM_DATA"

#: File name -> where to get it (shown when it is missing).
DATA_FILES = {
    "happy_buddha_20k.ply": (
        "the Stanford Happy Buddha decimated to about 20,000 triangles (the paper's 20,062). "
        "Get happy_recon.tar.gz from the Stanford 3D Scanning Repository "
        "(http://graphics.stanford.edu/data/3Dscanrep/), decimate happy_vrip_res3.ply or "
        "happy_vrip.ply to about 20k triangles (e.g. quadric decimation in MeshLab or "
        "Open3D) and save it as binary PLY named happy_buddha_20k.ply, in Stanford's "
        "coordinates (+Y up, base near y = 0.05)"),
}


class MissingDataError(FileNotFoundError):
    """A data file the scene needs is not where it was looked for."""


def find_data_file(name: str, data_dir: Optional[os.PathLike] = None) -> Path:
    """The path of data file ``name`` in ``data_dir`` or ``$PARTPM_DATA``.

    Raises
    ------
    MissingDataError
        Not found; the message says where it looked, what the file is, where to get it and
        where to put it.
    """
    looked = []
    candidates = []
    if data_dir is not None:
        candidates.append(("data_dir", Path(data_dir)))
    elif os.environ.get(DATA_ENV):
        candidates.append((DATA_ENV, Path(os.environ[DATA_ENV])))
    for label, directory in candidates:
        path = directory / name
        if path.is_file():
            return path
        looked.append(f"{label}={str(directory)!r}")
    where = ("looked in " + ", ".join(looked)) if looked else \
        f"no data directory given (argument data_dir / --data, or ${DATA_ENV})"
    about = DATA_FILES.get(name, "a data file of a built-in scene")
    raise MissingDataError(
        f"data file {name!r} not found: {where}. It is {about}. Put it in a directory and "
        f"set {DATA_ENV} to that directory (or pass --data DIR on the command line, "
        f"data_dir=DIR in Python).")
