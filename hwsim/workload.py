"""The per-map workloads that ``partpm speedup`` and ``partpm calibrate`` record and hwsim
replays (format: WORKLOAD.md). This module is the format's one owner: the recorders write a
workloads directory with :func:`save_workloads` and a directory of calibration sets (one
workloads directory per leaf size and radius) with :func:`save_workload_sets`; hwsim reads
them with :func:`load_workloads` and :func:`load_workload_sets`.

Version 2 adds, in ``meta.json``, the radius as a fraction of the scene (``radius_fraction``)
and the CPU threads the times were measured with (``threads``); version 3 the SIMD lanes that
ran each query (``lanes``: queries walk the tree side by side in packets of that many, in the
order of the per-query arrays) and the CPU's L1 data cache (``l1_bytes``). Older files still
load (those keys then read as null).

NumPy and JSON only: hwsim never imports Mitsuba.
"""
from __future__ import annotations

import json
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["MapWorkloads", "WorkloadSet", "load_workloads", "save_workloads", "folder_hint",
           "load_workload_sets", "save_workload_sets", "set_name", "FORMAT_VERSION",
           "READS_VERSIONS", "SETS_FILE"]

#: The version written.
FORMAT_VERSION = 3
#: The versions read: 1 lacks ``radius_fraction`` and ``threads``, 1 and 2 lack ``lanes``
#: and ``l1_bytes`` (read as None).
READS_VERSIONS = (1, 2, 3)
#: The index of a directory of calibration sets.
SETS_FILE = "sets.json"


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


def _read_json(path: Path) -> dict:
    """The JSON object in ``path``; a ValueError naming the file when it is not one."""
    try:
        document = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path} is not valid JSON ({e}): write it again with the command "
                         f"that made it") from None
    if not isinstance(document, dict):
        raise ValueError(f"{path} holds a JSON {type(document).__name__}, not an object (format "
                         f"in hwsim/WORKLOAD.md): write it again with the command that made it")
    return document


def folder_hint(d: Path) -> str:
    """Where inside ``d`` the workloads or sets are, for a message about ``d`` (a speedup
    run's or calibration's --out folder given for the folder inside it), or ''."""
    for inner, index in (("workloads", "meta.json"), ("sets", SETS_FILE)):
        if (d / inner / index).is_file():
            return f" (it has one inside: {d / inner})"
    return ""


def load_workloads(directory) -> tuple[dict, dict[int, MapWorkloads]]:
    """``(meta, {n: MapWorkloads})`` from a ``workloads/`` directory.

    Raises ValueError naming the file and what is wrong when the format does not match.
    """
    d = Path(directory)
    meta_path = d / "meta.json"
    if not meta_path.is_file():
        raise ValueError(f"{meta_path} is missing: is {d} a workloads directory written by "
                         f"'partpm speedup'? It is the speedup run's workloads/ folder"
                         f"{folder_hint(d)}")
    meta = _read_json(meta_path)
    if meta.get("version") not in READS_VERSIONS:
        raise ValueError(f"{meta_path}: format version {meta.get('version')!r}, this hwsim "
                         f"reads versions {', '.join(map(str, READS_VERSIONS))}")
    for key in ("radius_fraction", "threads", "leaf_size", "lanes", "l1_bytes"):
        meta.setdefault(key, None)
    for key in ("lanes", "l1_bytes"):
        _optional_count(key, meta[key], f"{meta_path}: ")
    for key in ("queries", "bytes_per_node", "bytes_per_photon"):
        if key not in meta:
            raise ValueError(f"{meta_path}: {key} is missing (format in hwsim/WORKLOAD.md)")
        _count(key, meta[key], f"{meta_path}: ")
    files = meta.get("files")
    if not isinstance(files, dict) or not files:
        raise ValueError(f"{meta_path}: files must map each n to its file, as "
                         f'{{"1": "n1.npz", ...}}, got {files!r}')
    loads, spelt = {}, {}
    for n_text, name in files.items():
        n = _count("files: n", int(n_text) if str(n_text).isdigit() else n_text,
                   f"{meta_path}: ")
        if n in spelt:
            raise ValueError(f"{meta_path}: files lists n = {n} twice (as {spelt[n]!r} and "
                             f"{n_text!r}): one file per n")
        spelt[n] = n_text
        loads[n] = _load_map_workloads(d / name, n, meta)
    _check_consistent(meta_path, meta, {n: (loads[n], d / files[spelt[n]]) for n in loads})
    return meta, loads


#: Bytes of a photon's position (float32 x, y, z): the least a photon record holds; the
#: memory model charges ``bytes_per_photon`` minus these per photon found.
POSITION_BYTES = 12


def _check_consistent(meta_path: Path, meta: dict, loads: dict):
    """The rules of WORKLOAD.md that tie the files together: a record holds at least a
    position; ``maps`` lists the n of ``files``; every n partitions the same photons (the
    same total, ``photons_stored`` where given); a map's bytes hold at least its photon
    records. The photons found summed over the maps are not held to n = 1's: a recorded
    workload's are (eq. (2)), a synthetic one need not be. ``loads``: {n: (its
    MapWorkloads, its file)}."""
    if meta["bytes_per_photon"] < POSITION_BYTES:
        raise ValueError(f"{meta_path}: bytes_per_photon must be >= {POSITION_BYTES} (a "
                         f"photon's position alone is 12 bytes), got {meta['bytes_per_photon']}")
    if "maps" in meta and sorted(meta["maps"]) != sorted(loads):
        raise ValueError(f"{meta_path}: maps lists n = {meta['maps']!r} but files has "
                         f"{sorted(loads)}: they must name the same n")
    stored = {n: int(w.map_photons.sum()) for n, (w, _) in loads.items()}
    want = meta.get("photons_stored")
    if want is not None and any(v != want for v in stored.values()) or \
            len(set(stored.values())) > 1:
        said = f"photons_stored = {want}, " if want is not None else ""
        raise ValueError(f"{meta_path}: every n must split the same photons ({said}map_photons "
                         f"summed per n: {dict(sorted(stored.items()))})")
    for n, (w, path) in sorted(loads.items()):
        short = w.map_bytes < w.map_photons * meta["bytes_per_photon"]
        if np.any(short):
            m = int(np.argmax(short))
            raise ValueError(f"{path}: "
                             f"map {m}'s map_bytes ({int(w.map_bytes[m])}) hold less than its "
                             f"{int(w.map_photons[m])} photons of {meta['bytes_per_photon']} "
                             f"bytes")


#: The arrays of one n's file, and their shape in terms of (n, Q); map_seconds is (n, R).
#: All but map_seconds are counts: whole numbers.
_ARRAYS = {"nodes_visited": "nq", "photons_tested": "nq", "photons_found": "nq",
           "map_photons": "n", "map_bytes": "n", "map_seconds": "nr"}


def _load_map_workloads(path: Path, n: int, meta: dict) -> MapWorkloads:
    """One n's :class:`MapWorkloads`, every array checked: present, of its shape, finite and
    >= 0, and no query finding more photons than it tested."""
    if not path.is_file():
        raise ValueError(f"{path} is missing (listed in meta.json's files)")
    q = meta["queries"]
    arrays = {}
    try:
        z = np.load(path)          # (no pickles: a file that holds one is refused)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile):
        raise ValueError(f"{path} is not a workload file (a NumPy .npz of arrays written by "
                         f"'partpm speedup'; format in hwsim/WORKLOAD.md)") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise ValueError(f"{path} is a single NumPy array, not a workload file (an .npz of "
                         f"the arrays in hwsim/WORKLOAD.md)")
    with z:
        for k, kind in _ARRAYS.items():
            if k not in z:
                raise ValueError(f"{path}: {k} is missing (format in hwsim/WORKLOAD.md)")
            try:
                a = z[k]
            except ValueError:       # an array of Python objects (pickled): not loaded
                raise ValueError(f"{path}: {k} is an array of Python objects; it must hold "
                                 f"numbers (format in hwsim/WORKLOAD.md)") from None
            if a.dtype.kind not in "iuf":
                raise ValueError(f"{path}: {k} must hold integers or floats (format in "
                                 f"hwsim/WORKLOAD.md), got dtype {a.dtype}")
            ok = {"nq": a.shape == (n, q), "n": a.shape == (n,),
                  "nr": a.ndim == 2 and a.shape[0] == n}[kind]
            if not ok:
                want = {"nq": f"({n}, {q})", "n": f"({n},)", "nr": f"({n}, repeats)"}[kind]
                raise ValueError(f"{path}: {k} has shape {a.shape}, expected {want}")
            if a.size and not (np.all(np.isfinite(a)) and a.min() >= 0):
                raise ValueError(f"{path}: {k} must be finite and >= 0, got a minimum of "
                                 f"{a.min()}")
            if k != "map_seconds" and a.size and not np.all(a == np.floor(a)):
                raise ValueError(f"{path}: {k} counts, so its values must be whole numbers "
                                 f"(WORKLOAD.md: integers), got {a[a != np.floor(a)][0]!r}")
            arrays[k] = a
    if np.any(arrays["photons_found"] > arrays["photons_tested"]):
        raise ValueError(f"{path}: photons_found exceeds photons_tested for some query (a "
                         f"query finds only photons it tested)")
    if q and not (arrays["nodes_visited"].any() or arrays["photons_tested"].any()):
        raise ValueError(f"{path}: no query visits a node or tests a photon of any map "
                         f"(nodes_visited and photons_tested are 0 throughout): there is no "
                         f"work to simulate")
    return MapWorkloads(n=n, **arrays, bytes_per_node=int(meta["bytes_per_node"]),
                        bytes_per_photon=int(meta["bytes_per_photon"]))


def _count(key: str, v, where: str = "") -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"{where}{key} must be an integer >= 1, got {v!r}")
    return v


def _optional_count(key: str, v, where: str = ""):
    """``v`` as an int, or None; ValueError naming ``key`` unless it is an integer >= 1."""
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
        raise ValueError(f"{where}{key} must be an integer >= 1 or null, got {v!r}")
    return int(v)


def save_workloads(directory, loads: dict, *, scene: str = "synthetic", radius: float = 0.0,
                   photons_emitted: int = 0, photons_stored: int | None = None,
                   leaf_size: int | None = None, radius_fraction: float | None = None,
                   threads: int | None = None, lanes: int | None = None,
                   l1_bytes: int | None = None) -> Path:
    """Write ``{n: MapWorkloads}`` in the WORKLOAD.md format. The bytes of a photon record
    and of a tree node are the workloads' own (the same for every n). ``radius_fraction``:
    the radius over the scene's longest side; ``threads``: the CPU threads that measured
    ``map_seconds``; ``lanes``: the SIMD lanes of one packet of queries in those runs, the
    per-query arrays being in the order the queries ran; ``l1_bytes``: the L1 data cache of
    the CPU that ran them (None: unknown, or not measured)."""
    lanes, l1_bytes = _optional_count("lanes", lanes), _optional_count("l1_bytes", l1_bytes)
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    queries = {w.queries for w in loads.values()}
    if len(queries) != 1:
        raise ValueError(f"every n must have the same queries, got counts {sorted(queries)}")
    if queries == {0}:
        raise ValueError("a workload needs at least one query (per-query figures divide by "
                         "the query count)")
    sizes = {(w.bytes_per_photon, w.bytes_per_node) for w in loads.values()}
    if len(sizes) != 1:
        raise ValueError(f"every n must have the same record and node bytes, got {sizes}")
    bytes_per_photon, bytes_per_node = sizes.pop()
    if photons_stored is None:
        photons_stored = int(next(iter(loads.values())).map_photons.sum())
    info = {"version": FORMAT_VERSION, "scene": scene, "queries": queries.pop(),
            "radius": radius, "photons_emitted": photons_emitted,
            "photons_stored": photons_stored, "leaf_size": leaf_size,
            "radius_fraction": radius_fraction, "threads": threads, "lanes": lanes,
            "l1_bytes": l1_bytes,
            "bytes_per_photon": int(bytes_per_photon), "bytes_per_node": int(bytes_per_node),
            "maps": sorted(loads), "files": {str(n): f"n{n}.npz" for n in sorted(loads)}}
    # A folder written before with other map counts: their files go, so the folder holds
    # what its meta.json lists and no stale workload beside it.
    for old in d.glob("n*.npz"):
        if re.fullmatch(r"n\d+\.npz", old.name) and int(old.stem[1:]) not in loads:
            old.unlink()
    for n, w in loads.items():
        np.savez_compressed(d / f"n{n}.npz", nodes_visited=w.nodes_visited,
                            photons_tested=w.photons_tested, photons_found=w.photons_found,
                            map_photons=w.map_photons, map_bytes=w.map_bytes,
                            map_seconds=w.map_seconds, version=np.int64(FORMAT_VERSION))
    (d / "meta.json").write_text(json.dumps(info, indent=2) + "\n")
    return d


@dataclass
class WorkloadSet:
    """One calibration set: the workloads of every n at one leaf size and one radius."""

    name: str                      # its folder in the sets directory, e.g. "leaf8_r0.025"
    meta: dict                     # its meta.json (leaf_size, radius, radius_fraction, ...)
    loads: dict                    # {n: MapWorkloads}

    @property
    def leaf_size(self):
        return self.meta.get("leaf_size")

    @property
    def radius(self) -> float:
        return float(self.meta.get("radius", 0.0))


def set_name(leaf_size, radius_fraction) -> str:
    """The folder of the set of ``leaf_size`` and ``radius_fraction``: ``leaf8_r0.025``."""
    return f"leaf{leaf_size}_r{radius_fraction:g}"


def save_workload_sets(directory, sets, *, scene: str, settings: dict | None = None) -> Path:
    """Write calibration sets: every :class:`WorkloadSet` ``s`` (its ``meta`` holding at
    least ``leaf_size``, ``radius`` and the keywords of :func:`save_workloads`) as a workloads
    directory ``directory/s.name/``, and the index ``directory/sets.json`` (WORKLOAD.md):
    the scene, ``settings`` (how the sets were measured) and per set its folder, leaf size,
    radius and radius fraction."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    keys = ("radius", "photons_emitted", "photons_stored", "leaf_size", "radius_fraction",
            "threads", "lanes", "l1_bytes")
    index = []
    for s in sets:
        save_workloads(d / s.name, s.loads, scene=scene,
                       **{k: s.meta[k] for k in keys if k in s.meta})
        index.append({"name": s.name, "leaf_size": s.meta.get("leaf_size"),
                      "radius": s.meta.get("radius"),
                      "radius_fraction": s.meta.get("radius_fraction"),
                      "maps": sorted(s.loads)})
    names = [s["name"] for s in index]
    if len(set(names)) != len(names):
        raise ValueError(f"calibration sets must have distinct names, got {names}")
    (d / SETS_FILE).write_text(json.dumps(
        {"version": FORMAT_VERSION, "scene": scene, "settings": settings or {},
         "sets": index}, indent=2) + "\n")
    return d


def load_workload_sets(directory) -> tuple[dict, list[WorkloadSet]]:
    """``(index, [WorkloadSet])`` from a directory of calibration sets (``sets.json``), or,
    from a plain workloads directory (``meta.json``), that one workload as the only set.

    Raises ValueError naming the file and what is wrong."""
    d = Path(directory)
    index_path = d / SETS_FILE
    if not index_path.is_file():
        if (d / "meta.json").is_file():
            meta, loads = load_workloads(d)
            return ({"scene": meta.get("scene", str(d)), "settings": {}, "sets": []},
                    [WorkloadSet(d.name or "workloads", meta, loads)])
        raise ValueError(f"{d} holds neither {SETS_FILE} (calibration sets written by "
                         f"'partpm calibrate') nor meta.json (a workloads directory)"
                         f"{folder_hint(d)}")
    index = _read_json(index_path)
    if index.get("version") not in READS_VERSIONS:
        raise ValueError(f"{index_path}: format version {index.get('version')!r}, this hwsim "
                         f"reads versions {', '.join(map(str, READS_VERSIONS))}")
    if not index.get("sets"):
        raise ValueError(f"{index_path} lists no sets")
    sets = []
    for entry in index["sets"]:
        meta, loads = load_workloads(d / entry["name"])
        for key in ("leaf_size", "radius", "radius_fraction"):
            if entry.get(key) != meta.get(key):
                raise ValueError(f"{index_path}: set {entry['name']} has {key} "
                                 f"{entry.get(key)!r}, its meta.json {meta.get(key)!r}")
        sets.append(WorkloadSet(entry["name"], meta, loads))
    return index, sets
