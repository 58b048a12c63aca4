"""Reading the per-map workloads that ``partpm speedup`` records (format: WORKLOAD.md).

NumPy and JSON only: hwsim never imports Mitsuba.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["MapWorkloads", "load_workloads", "FORMAT_VERSION"]

FORMAT_VERSION = 1


@dataclass
class MapWorkloads:
    """The workload of one n: n maps, each answering the same Q queries."""

    n: int
    nodes_visited: np.ndarray      # (n, Q)
    photons_tested: np.ndarray     # (n, Q)
    photons_found: np.ndarray      # (n, Q)
    map_photons: np.ndarray        # (n,)
    map_bytes: np.ndarray          # (n,)
    map_seconds: np.ndarray        # (n, repeats), measured; may be empty for synthetic loads

    @property
    def queries(self) -> int:
        return int(self.nodes_visited.shape[1])


def load_workloads(directory) -> tuple[dict, dict[int, MapWorkloads]]:
    """``(meta, {n: MapWorkloads})`` from a ``workloads/`` directory.

    Raises ValueError naming the file and what is wrong when the format does not match.
    """
    d = Path(directory)
    meta_path = d / "meta.json"
    if not meta_path.is_file():
        raise ValueError(f"{meta_path} is missing: is {d} a workloads directory written by "
                         f"'partpm speedup'?")
    meta = json.loads(meta_path.read_text())
    if meta.get("version") != FORMAT_VERSION:
        raise ValueError(f"{meta_path}: format version {meta.get('version')!r}, this hwsim "
                         f"reads version {FORMAT_VERSION}")
    loads = {}
    for n_text, name in meta["files"].items():
        n = int(n_text)
        with np.load(d / name) as z:
            w = MapWorkloads(n=n, **{k: z[k] for k in (
                "nodes_visited", "photons_tested", "photons_found", "map_photons",
                "map_bytes", "map_seconds")})
        for k in ("nodes_visited", "photons_tested", "photons_found"):
            shape = getattr(w, k).shape
            if shape != (n, meta["queries"]):
                raise ValueError(f"{d / name}: {k} has shape {shape}, expected "
                                 f"({n}, {meta['queries']})")
        loads[n] = w
    return meta, loads
