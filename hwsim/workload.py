"""The per-map workloads that ``partpm speedup`` records and hwsim replays (format:
WORKLOAD.md). This module is the format's one owner: the recorder writes it with
:func:`save_workloads`, hwsim reads it with :func:`load_workloads`.

NumPy and JSON only: hwsim never imports Mitsuba.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["MapWorkloads", "load_workloads", "save_workloads", "FORMAT_VERSION"]

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
    bytes_per_node: int            # of one internal tree node (meta.json)
    bytes_per_photon: int          # of one photon record (meta.json)
    _tile_counts: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def queries(self) -> int:
        return int(self.nodes_visited.shape[1])

    def tile_counts(self, tile_queries: int) -> tuple:
        """(nodes, tested, found, sizes): the counts summed per map over tiles of
        ``tile_queries`` queries, as float64 (n, K) arrays, and the queries per tile (K,).
        Computed once per tile size: every simulation of a sweep reuses them."""
        if tile_queries not in self._tile_counts:
            q = self.queries
            starts = np.arange(0, q, tile_queries)
            sizes = np.diff(np.append(starts, q))

            def per_tile(a):
                if q == 0:
                    return np.zeros((a.shape[0], 0))
                return np.add.reduceat(np.asarray(a, dtype=np.float64), starts, axis=1)
            self._tile_counts[tile_queries] = (per_tile(self.nodes_visited),
                                               per_tile(self.photons_tested),
                                               per_tile(self.photons_found), sizes)
        return self._tile_counts[tile_queries]


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
                "map_bytes", "map_seconds")}, bytes_per_node=int(meta["bytes_per_node"]),
                bytes_per_photon=int(meta["bytes_per_photon"]))
        for k in ("nodes_visited", "photons_tested", "photons_found"):
            shape = getattr(w, k).shape
            if shape != (n, meta["queries"]):
                raise ValueError(f"{d / name}: {k} has shape {shape}, expected "
                                 f"({n}, {meta['queries']})")
        loads[n] = w
    return meta, loads


def save_workloads(directory, loads: dict, *, scene: str = "synthetic", radius: float = 0.0,
                   photons_emitted: int = 0, photons_stored: int | None = None,
                   leaf_size: int | None = None) -> Path:
    """Write ``{n: MapWorkloads}`` in the WORKLOAD.md format. The bytes of a photon record
    and of a tree node are the workloads' own (the same for every n)."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    queries = {w.queries for w in loads.values()}
    if len(queries) != 1:
        raise ValueError(f"every n must have the same queries, got counts {sorted(queries)}")
    sizes = {(w.bytes_per_photon, w.bytes_per_node) for w in loads.values()}
    if len(sizes) != 1:
        raise ValueError(f"every n must have the same record and node bytes, got {sizes}")
    bytes_per_photon, bytes_per_node = sizes.pop()
    if photons_stored is None:
        photons_stored = int(next(iter(loads.values())).map_photons.sum())
    info = {"version": FORMAT_VERSION, "scene": scene, "queries": queries.pop(),
            "radius": radius, "photons_emitted": photons_emitted,
            "photons_stored": photons_stored, "leaf_size": leaf_size,
            "bytes_per_photon": int(bytes_per_photon), "bytes_per_node": int(bytes_per_node),
            "maps": sorted(loads), "files": {str(n): f"n{n}.npz" for n in sorted(loads)}}
    for n, w in loads.items():
        np.savez_compressed(d / f"n{n}.npz", nodes_visited=w.nodes_visited,
                            photons_tested=w.photons_tested, photons_found=w.photons_found,
                            map_photons=w.map_photons, map_bytes=w.map_bytes,
                            map_seconds=w.map_seconds, version=np.int64(FORMAT_VERSION))
    (d / "meta.json").write_text(json.dumps(info, indent=2) + "\n")
    return d
