"""Reports of a simulated PE array over the recorded workloads: tables, CSV/JSON, plots, sweeps.

For every recorded n the array has one PE per map (the paper's proposal) and the frame is
simulated with and without the gather; the speedup against n = 1 shows what the gather costs,
with the configured gather network and, in ``networks``, with every other one.
For the largest n, a sweep over PE counts P (maps shared round-robin, a PE's maps sharing its
SRAM) and gather networks (a bus; trees and rings, pipelined and store-and-forward) shows
where adding PEs stops paying: the first P from which the next P of the sweep (twice as many, or n)
shortens the frame by less than 5%. A second sweep puts every map in DRAM (no SRAM) and lets the PEs share 1 or 4 DRAM
channels, or have one each: the discrete-event model shows where contention for the
channels, not the gather, ends the scaling. Every row of every table (per n, sweep,
contention, sensitivity) carries the bytes a frame reads from DRAM over all PEs
(``dram_bytes``).
"""
from __future__ import annotations

import csv
import json
import os
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .config import CYCLE_KEYS, HardwareConfig
from .model import simulate
from .networks import SWEEP
from .workload import folder_hint, load_workloads

__all__ = ["run_report", "format_report", "sensitivity", "ASSUMED"]

#: The constants an FPGA design would fix, which this model can only assume.
ASSUMED = ("cycles_per_node", "cycles_per_test", "cycles_per_accumulate",
           "outstanding_queries", "memory.sram_bytes", "memory.dram_bytes_per_cycle",
           "memory.dram_latency_cycles", "gather.hop_latency_cycles",
           "gather.link_bytes_per_cycle", "gather.adder_latency_cycles",
           "energy.pj_per_node", "energy.pj_per_test", "energy.pj_per_accumulate",
           "energy.pj_per_dram_byte", "energy.pj_per_link_byte", "energy.pj_per_add",
           "energy.static_watts_per_pe")


def _scaled(config, name, factor):
    """``config`` with the constant ``name`` ("key" or "group.key") times ``factor`` (integers
    rounded, and kept >= 1), or None where the scaled value leaves the constant's allowed
    range (a value near the top of it, doubled)."""
    group, _, key = name.rpartition(".")
    value = getattr(getattr(config, group) if group else config, key)
    new = max(1, int(round(value * factor))) if isinstance(value, int) else value * factor
    try:
        return config.with_(**({group: {key: new}} if group else {key: new}))
    except ValueError as e:
        if str(e).startswith(f"{name} must be"):       # the value, out of its range
            return None
        raise


def _ratio(a: float, b: float):
    """``a / b``, None where ``b`` is 0 (a frame at the smallest n that costs no energy: every
    constant it would pay is 0, e.g. a config of link and adder energy alone with one PE,
    which gathers nothing)."""
    return a / b if b else None


def swept_constants(config) -> tuple:
    """The constants the sensitivity sweep varies: :data:`ASSUMED`, less the ``cycles_per_*``
    with fitted compute costs."""
    fitted = config.pe.costs == "fitted"
    return tuple(n for n in ASSUMED if not (fitted and n in CYCLE_KEYS))


def sensitivity(config, loads, factors=(0.5, 2.0)) -> list:
    """Each assumed constant times 0.5 and 2: the speedup at the largest n (with the gather,
    one PE per map), the gather's share of the frame and the energy of a frame at the largest
    n over that at the smallest (None where that frame costs no energy), against the unchanged
    config. With fitted compute costs (``[pe] costs = "fitted"``) the ``cycles_per_*``
    constants are not assumed, and not swept (:func:`swept_constants`). A scaling that leaves
    a constant's allowed range (a value near its top, doubled) has a row with ``"skipped"``
    saying so and None for every figure."""
    ns = sorted(loads)
    first, last = ns[0], ns[-1]

    def measure(cfg):
        a = simulate(cfg.with_(pe_count=first), loads[first])
        b = simulate(cfg.with_(pe_count=last), loads[last])
        return {"speedup": a.frame_cycles / b.frame_cycles, "gather_share": b.gather_share,
                "energy_ratio": _ratio(b.energy_joules, a.energy_joules),
                "dram_bytes": _dram_bytes(b), "dram_bytes_smallest_n": _dram_bytes(a)}
    rows = [{"constant": "(as configured)", "factor": 1.0, **measure(config)}]
    for name in swept_constants(config):
        for f in factors:
            scaled = _scaled(config, name, f)
            if scaled is None:
                rows.append({**dict.fromkeys(rows[0]), "constant": name, "factor": f,
                             "skipped": f"x{f:g} leaves its allowed range"})
            else:
                rows.append({"constant": name, "factor": f, **measure(scaled)})
    return rows


def _dram_bytes(report) -> float:
    """Bytes one frame reads from DRAM, over all PEs."""
    return float(report.dram_bytes.sum())


#: The gather networks of the sweep: (label, topology, pipelined), every variant of
#: :data:`hwsim.networks.NETWORKS`.
GATHERS = SWEEP

#: DRAM channels of the contention sweep: 0 is one private channel per PE.
CONTENTION_CHANNELS = (0, 4, 1)


def _channels_label(channels):
    return "private" if channels == 0 else f"{channels} shared"


def _add_speedups(rows, group: str):
    """Speedup (and efficiency) of each row against the first row of its ``group``."""
    for row in rows:
        first = next(x for x in rows if x[group] == row[group])
        row["speedup"] = first["frame_cycles"] / row["frame_cycles"]
        row["efficiency"] = row["speedup"] * first["pe_count"] / row["pe_count"]


def _saturation(points) -> int:
    """The first PE count from which the next of the sweep (twice as many PEs, or n, the
    last) shortens the frame by less than 5%."""
    for a, b in zip(points, points[1:]):
        if b["frame_cycles"] > 0.95 * a["frame_cycles"]:
            return a["pe_count"]
    return points[-1]["pe_count"]


def calibration(loads, meta, check_dir=None) -> dict:
    """Fit CPU costs to this workload's measured per-map times (:func:`hwsim.calibrate.
    calibrate`: costs, standard errors, bootstrap intervals, the costs fitted to 0 and the
    design's conditioning) and check them on itself and, given ``check_dir`` (another
    scene's workloads, or its calibration sets), on that. One speedup run varies nodes,
    tests and found photons together: its ``design`` says how collinear they are, and
    ``zero`` which costs it could not identify (``partpm calibrate`` records the sets that
    can)."""
    from .calibrate import calibrate, check
    from .workload import WorkloadSet, load_workload_sets
    if any(w.map_seconds.size == 0 for w in loads.values()):
        return {"skipped": "the workloads have no measured map_seconds (R = 0, a synthetic "
                           "workload): no costs to fit"}
    try:
        # The workload's own meta: its packets' lanes and L1 cache enter the fit.
        f = calibrate(WorkloadSet(meta.get("scene", "workloads"), meta, loads))
    except ValueError as e:
        return {"skipped": str(e)}
    out = {"fit_on": meta.get("scene", ""), **f.as_dict()}
    if check_dir is not None:
        other_index, other = load_workload_sets(check_dir)
        out["other_scene"] = other_index.get("scene", str(check_dir))
        out["other"] = check(f.costs, other)
        # Costs are CPU seconds per action at the threads that measured them: times
        # measured with other threads are not comparable (hwsim's configs convert by
        # threads; the check says so rather than guess the threads' speedup).
        threads = {s.meta.get("threads") for s in other} - {None}
        own = meta.get("threads")
        if own is not None and threads and threads != {own}:
            out["threads_differ"] = (f"{meta.get('scene', 'this workload')}'s times were "
                                     f"measured with {own} thread{'s' * (own != 1)}, "
                                     f"{out['other_scene']}'s with "
                                     f"{', '.join(map(str, sorted(threads)))}: the check "
                                     f"compares unlike seconds (measure both with the same "
                                     f"--threads)")
    return out


def pe_costs(config) -> dict:
    """The compute costs the model ran on: cycles per node, test, found photon and map run,
    "assumed" or "fitted" (and then the file, its scene and the conversion rule)."""
    c = config.compute_cycles()
    out = {"source": c["source"], "cycles_per_node": c["node"], "cycles_per_test": c["test"],
           "cycles_per_found": c["found"], "cycles_per_map": c["map"]}
    if c["source"] == "fitted":
        pe = config.pe
        out.update(fitted_costs=pe.fitted_costs, fitted_scene=pe.fitted_scene,
                   threads=pe.threads,
                   rule="a PE as fast as one measured CPU thread: cycles per node / test / "
                        "found = CPU seconds per action x threads x clock_hz; cycles per "
                        "map = CPU seconds per map run x clock_hz")
    return out


def run_report(workload_dir, config: HardwareConfig, out_dir, check_dir=None,
               progress=None, code=None, out_name: str = "the output folder") -> dict:
    """Simulate every recorded n, sweep PEs, topologies, DRAM sharing and the assumed
    constants, calibrate on the measured times (and check on ``check_dir``); write the files.
    ``progress``: called with a line before each phase (None: silent). ``code``: the version
    of the code that runs the report, recorded in ``report.json`` (hwsim does not import the
    renderer, whose sources the version is a hash of: the caller passes it in).
    ``out_name``: what to call ``out_dir`` where it cannot be made (``--out`` on the
    command line)."""
    say = progress or (lambda *a: None)
    check_out_folder(out_dir, out_name)         # before the workloads are read
    meta, loads = load_workloads(workload_dir)
    check_dir = None if check_dir is None else Path(check_dir)
    if check_dir is not None and not ((check_dir / "meta.json").is_file()
                                      or (check_dir / "sets.json").is_file()):
        # Before any simulation, and before the output folder is made.
        raise ValueError(f"check: {check_dir} holds neither sets.json (calibration sets "
                         f"written by 'partpm calibrate') nor meta.json (a workloads "
                         f"directory){folder_hint(check_dir)}")
    if check_dir is not None:
        _check_measured(loads, check_dir)
    say(f"{meta.get('scene', workload_dir)}: n = {', '.join(map(str, sorted(loads)))}, "
        f"{meta['queries']} queries per map")
    out = Path(out_dir)
    try:                                    # made and written to before the simulation
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".probe{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise ValueError(f"the output folder {out} cannot be made or written: "
                         f"{e.strerror or e}") from None
    rows, detail = _per_n(config, loads)
    n_max = max(loads)
    pes = [2 ** i for i in range(n_max.bit_length()) if 2 ** i <= n_max]
    if n_max not in pes:
        pes.append(n_max)
    say(f"sweeping P and the gather network at n = {n_max} ...")
    sweep = _network_sweep(config, loads[n_max], pes)
    say("sweeping shared DRAM channels (event model) ...")
    contention = _contention_sweep(config, loads[n_max], pes)
    say("every gather network with one PE per map, every n ...")
    networks = _networks_per_n(config, loads)
    say(f"sensitivity: {len(swept_constants(config))} constants x0.5 and x2 ...")
    sens = sensitivity(config, loads)
    result = {**({"code": code} if code else {}), "config": asdict(config),
        "workload": {k: meta[k] for k in (
            "scene", "queries", "radius", "photons_stored") if k in meta},
        "rows": rows, "networks": networks, "sweep": sweep,
        "saturation_pe_count": {g[0]: _saturation([s for s in sweep if s["gather"] == g[0]])
                                for g in GATHERS},
        "contention": contention,
        "contention_saturation_pe_count": {
            _channels_label(ch): _saturation([c for c in contention
                                              if c["dram_channels"] == ch])
            for ch in CONTENTION_CHANNELS},
        "sensitivity": sens, "calibration": calibration(loads, meta, check_dir),
        "largest_n": detail.as_dict()}
    result["pe_costs"] = pe_costs(config)
    _write(out, result)
    _plots(rows, sweep, contention, detail, out, meta.get("scene", ""))
    return result


def _check_measured(loads, check_dir: Path):
    """Before any simulation: ``--check`` fits costs to these workloads' measured map times
    and checks them on ``check_dir``'s, so both must have some (a ValueError naming which
    has none)."""
    from .workload import load_workload_sets
    if any(w.map_seconds.size == 0 for w in loads.values()):
        raise ValueError(f"check: the workloads have no measured map_seconds (R = 0), so "
                         f"there are no costs to fit and check on {check_dir}: drop the "
                         f"check, or give workloads written by 'partpm speedup'")
    _, other = load_workload_sets(check_dir)
    for s in other:
        for n, w in s.loads.items():
            if w.map_seconds.size == 0 or not np.all(w.map_seconds > 0):
                raise ValueError(f"check: {check_dir} (n = {n}) has no measured map_seconds "
                                 f"(R = 0) or a time of 0: the fitted costs cannot be checked "
                                 f"on it")


def check_out_folder(out, name: str):
    """A ValueError naming ``name`` where the folder ``out`` cannot be made or written (an
    empty name, a file on its way, a folder above it that cannot be written); nothing is
    made here (the report makes it once its inputs are read)."""
    if not str(out).strip():
        raise ValueError(f"{name} needs a folder, got {str(out)!r}")
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{name} {str(out)!r} is a file: the report writes a folder of files")
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(f"{name} {str(out)!r} cannot be made: {str(existing)!r} is a file, "
                         f"not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(f"{name} {str(out)!r} cannot be made or written: {str(existing)!r} "
                         f"is not writable")


def _per_n(config, loads):
    """One PE per map for every recorded n: rows with speedups against the smallest n, and
    the largest n's frame (for the per-PE plots). ``dram_bytes`` is the frame's, over all PEs;
    ``dram_bytes_max`` the busiest PE's."""
    ns = sorted(loads)
    rows = []
    base_nodes = float(loads[ns[0]].nodes_visited.sum()) if ns[0] == 1 else None
    for n in ns:
        r = simulate(config.with_(pe_count=n), loads[n])
        rows.append({"n": n, "pe_count": n, "frame_cycles": r.frame_cycles,
                     "compute_cycles": r.compute_cycles, "gather_cycles": r.gather_cycles,
                     "seconds": r.seconds, "frames_per_second": r.frames_per_second,
                     "queries_per_second": r.queries_per_second,
                     "load_imbalance": r.load_imbalance, "gather_share": r.gather_share,
                     "utilisation_mean": float(r.utilisation.mean()),
                     "dram_bytes": _dram_bytes(r),
                     "dram_bytes_max": float(r.dram_bytes.max()),
                     "energy_mj": r.energy_joules * 1e3,
                     "nj_per_query": r.energy_joules / r.queries * 1e9,
                     # (None without n = 1: report.json stays strict JSON)
                     "replicated_traversal": (r.nodes_visited / base_nodes
                                              if base_nodes else None)})
        if r.frame_cycles <= 0 or r.compute_cycles <= 0:
            raise ValueError(f"the frame of n = {n} takes 0 cycles of compute: the config "
                             f"charges nothing for what this workload does (its queries visit "
                             f"{int(loads[n].nodes_visited.sum()):,} nodes, test "
                             f"{int(loads[n].photons_tested.sum()):,} photons and find "
                             f"{int(loads[n].photons_found.sum()):,}): give those actions a "
                             f"cost (cycles_per_node, cycles_per_test, "
                             f"cycles_per_accumulate)")
        largest = r
    for row in rows:
        row["speedup"] = rows[0]["frame_cycles"] / row["frame_cycles"]
        row["speedup_without_gather"] = rows[0]["compute_cycles"] / row["compute_cycles"]
        row["efficiency"] = row["speedup"] / row["n"] * rows[0]["n"]
    return rows, largest


def _network_sweep(config, workload, pes) -> list:
    """Every gather network of :data:`GATHERS` on every P of ``pes``."""
    sweep = []
    for label, topology, pipelined in GATHERS:
        for p in pes:
            cfg = config.with_(pe_count=p,
                               gather={"topology": topology, "pipelined": pipelined})
            r = simulate(cfg, workload)
            sweep.append({"gather": label, "topology": topology, "pipelined": pipelined,
                          "pe_count": p, "frame_cycles": r.frame_cycles,
                          "gather_cycles": r.gather_cycles, "seconds": r.seconds,
                          "gather_share": r.gather_share, "dram_bytes": _dram_bytes(r)})
    _add_speedups(sweep, "gather")
    return sweep


def _networks_per_n(config, loads) -> list:
    """Every gather network of :data:`GATHERS` with one PE per map (P = n), for every
    recorded n: the gather's share of the frame as the array grows with the maps."""
    rows = []
    for label, topology, pipelined in GATHERS:
        for n in sorted(loads):
            cfg = config.with_(pe_count=n, gather={"topology": topology, "pipelined": pipelined})
            r = simulate(cfg, loads[n])
            rows.append({"gather": label, "topology": topology, "pipelined": pipelined,
                         "n": n, "pe_count": n, "frame_cycles": r.frame_cycles,
                         "gather_cycles": r.gather_cycles, "gather_share": r.gather_share,
                         "dram_bytes": _dram_bytes(r)})
    return rows


def _contention_sweep(config, workload, pes) -> list:
    """Every map in DRAM, the PEs sharing :data:`CONTENTION_CHANNELS` channels."""
    contention = []
    for channels in CONTENTION_CHANNELS:
        for p in pes:
            cfg = config.with_(pe_count=p, memory={"sram_bytes": 0, "dram_channels": channels})
            r = simulate(cfg, workload)
            contention.append({"dram_channels": channels, "pe_count": p, "model": r.model,
                               "frame_cycles": r.frame_cycles, "seconds": r.seconds,
                               "dram_bytes": _dram_bytes(r),
                               "stall_share": float(r.pe_stall.sum() / (
                                   r.pe_busy.sum() + r.pe_stall.sum())),
                               "channel_utilisation": float(
                                   r.dram_channel_busy.max() / r.compute_cycles)})
    _add_speedups(contention, "dram_channels")
    return contention


def _write(out: Path, result: dict):
    (out / "report.json").write_text(json.dumps(result, indent=2) + "\n")
    for name, key in (("report.csv", "rows"), ("sweep.csv", "sweep"),
                      ("sensitivity.csv", "sensitivity"), ("contention.csv", "contention")):
        data = result[key]
        with open(out / name, "w", newline="") as f:
            # every key of every row (a skipped sensitivity row adds one)
            writer = csv.DictWriter(f, fieldnames=list(dict.fromkeys(k for r in data for k in r)))
            writer.writeheader()
            writer.writerows(data)


def _plots(rows, sweep, contention, detail, out, scene):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    n = [r["n"] for r in rows]
    fig, ax = plt.subplots(1, 4, figsize=(18, 4))
    ax[0].plot(n, [m / n[0] for m in n], "k--", label="ideal")
    ax[0].plot(n, [r["speedup_without_gather"] for r in rows], "s:", label="without gather")
    ax[0].plot(n, [r["speedup"] for r in rows], "o-", label="with gather")
    ax[0].set_xscale("log", base=2)
    ax[0].set_yscale("log", base=2)
    ax[0].set_xlabel("maps n = PEs")
    ax[0].set_ylabel(f"frame speedup vs n = {n[0]}")
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"{scene}: simulated speedup", fontsize=10)
    ax[1].bar(range(detail.pe_count), detail.utilisation)
    ax[1].set_xlabel("PE")
    ax[1].set_ylabel("utilisation (busy / frame)")
    ax[1].set_title(f"n = {detail.map_count}: utilisation per PE", fontsize=10)
    styles = {"bus": "s--", "tree": "o-", "tree s&f": "o:", "ring": "^-", "ring s&f": "v:"}
    for label, _, _ in GATHERS:
        pts = [s for s in sweep if s["gather"] == label]
        ax[2].plot([s["pe_count"] for s in pts], [s["seconds"] * 1e3 for s in pts],
                   styles.get(label, "o-"), label=label, markersize=5 if "s&f" in label else 6)
    ax[2].set_xscale("log", base=2)
    ax[2].set_yscale("log")
    ax[2].set_xlabel("PEs P")
    ax[2].set_ylabel("frame time (ms)")
    ax[2].set_title(f"n = {detail.map_count}: PE count and gather network", fontsize=10)
    ax[2].legend(fontsize=8)
    for ch in CONTENTION_CHANNELS:
        pts = [c for c in contention if c["dram_channels"] == ch]
        ax[3].plot([c["pe_count"] for c in pts], [c["speedup"] for c in pts], "o-",
                   label=f"DRAM: {_channels_label(ch)}")
    ax[3].set_xscale("log", base=2)
    ax[3].set_yscale("log", base=2)
    ax[3].set_xlabel("PEs P")
    ax[3].set_ylabel("speedup vs P = 1")
    ax[3].set_title(f"n = {detail.map_count}, every map in DRAM: contention", fontsize=10)
    ax[3].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "hwsim.png", dpi=110)
    plt.close(fig)


def _or_na(value, width):
    return f"{value:{width}.2f}" if value is not None and value == value \
        else "n/a".rjust(width)


def format_report(result) -> str:
    """The report as text: the per-n table, the P x gather network table, and one line each
    for shared DRAM, the calibration and the sensitivity sweep. Every table row and line gives
    the frame's DRAM traffic (MB read per frame, over all PEs)."""
    n = result["largest_n"]["map_count"]
    head = []
    if result.get("pe_costs"):
        head.append(_format_pe_costs(result["pe_costs"]))
    if result.get("config"):
        head.append(_format_gather(result["config"]))
    lines = head + _format_rows(result["rows"]) + _format_sweep(result, n)
    if result.get("contention"):
        lines.append(_format_contention(result, n))
    cal = result.get("calibration")
    if cal:
        lines.append(_format_calibration(cal))
    if result.get("sensitivity"):
        lines.append(_format_sensitivity(result["sensitivity"], n, result["rows"][0]["n"]))
    return "\n".join(lines)


def _mb(nbytes) -> float:
    return nbytes / 1e6


def _format_rows(rows) -> list:
    lines = [] if rows[0]["n"] == 1 else [
        f"speedups against n = {rows[0]['n']}, the smallest n recorded (no run of one map)"]
    lines += [f"{'n=PEs':>5} {'frame ms':>9} {'fps':>8} {'speedup':>8} {'w/o gather':>10} "
             f"{'gather %':>8} {'imbalance':>9} {'util':>5} {'DRAM MB':>8} {'nodes x':>7} "
             f"{'mJ':>8} {'nJ/query':>8}"]
    for r in rows:
        lines.append(f"{r['n']:5d} {r['seconds'] * 1e3:9.2f} {r['frames_per_second']:8.2f} "
                     f"{r['speedup']:8.2f} {r['speedup_without_gather']:10.2f} "
                     f"{r['gather_share'] * 100:8.2f} {r['load_imbalance']:9.3f} "
                     f"{r['utilisation_mean']:5.2f} {_mb(r['dram_bytes']):8.1f} "
                     f"{_or_na(r['replicated_traversal'], 7)} {r['energy_mj']:8.3f} "
                     f"{r['nj_per_query']:8.1f}")
    return lines


def _format_sweep(result, n) -> list:
    """Frame ms (speedup) per P and gather network, and the DRAM MB per frame of each P (the
    same for every network: the network does not change which maps stay in SRAM)."""
    sweep = result["sweep"]
    lines = [f"n = {n} maps on P PEs: frame ms (speedup vs P = 1) per gather network "
             f"(s&f: store-and-forward), DRAM MB per frame"]
    labels = list(dict.fromkeys(s["gather"] for s in sweep))
    lines.append(f"{'P':>5} " + " ".join(f"{t:>16}" for t in labels) + f" {'DRAM MB':>9}")
    by = {(s["gather"], s["pe_count"]): s for s in sweep}
    for p in sorted({s["pe_count"] for s in sweep}):
        lines.append(f"{p:5d} " + " ".join(
            f"{by[t, p]['seconds'] * 1e3:8.1f} ({by[t, p]['speedup']:5.1f}x)".rjust(16)
            for t in labels) + f" {_mb(by[labels[0], p]['dram_bytes']):9.1f}")
    parts = [f"{k}: P = {v}" if v < n else f"{k}: still paying at P = {v} = n"
             for k, v in result["saturation_pe_count"].items()]
    lines.append(f"where the next P (twice the PEs, or n) gains under 5% (n = {n}): "
                 f"{'; '.join(parts)}")
    return lines


def _format_contention(result, n) -> str:
    contention = result["contention"]
    parts = []
    for label, p in result["contention_saturation_pe_count"].items():
        best = max((c for c in contention if _channels_label(c["dram_channels"]) == label),
                   key=lambda c: c["speedup"])
        where = f"from P = {p} the next P gains under 5%" if p < n else \
            f"still paying at P = {p} = n"
        parts.append(f"{label}: {where} (best speedup {best['speedup']:.1f} at "
                     f"P = {best['pe_count']})")
    traffic = sorted({round(_mb(c["dram_bytes"]), 1) for c in contention})
    mb = (f"{traffic[0]:.1f}" if len(traffic) == 1 else
          f"{traffic[0]:.1f}-{traffic[-1]:.1f}")
    return (f"every map in DRAM (n = {n}, {mb} MB from DRAM per frame), DRAM channels "
            f"{'; '.join(parts)}")


def _format_gather(config) -> str:
    """The gather network and schedule the per-n table's speedups and gather share are
    of (the config's)."""
    g = config["gather"]
    pipelined = ", pipelined" if g["pipelined"] and g["topology"] != "bus" else ""
    return (f"gather in the per-n table: {g['topology']}{pipelined}, "
            f"{g['link_bytes_per_cycle']:g} bytes/cycle per link, {g['hop_latency_cycles']:g} "
            f"cycles per hop, schedule '{config['gather_schedule']}'")


def _format_pe_costs(c) -> str:
    text = (f"PE compute costs ({c['source']}): {c['cycles_per_node']:.3g} cycles/node, "
            f"{c['cycles_per_test']:.3g}/test, {c['cycles_per_found']:.3g}/found, "
            f"{c['cycles_per_map']:.3g}/map run")
    if c["source"] == "fitted":
        text += (f", fitted on {c['fitted_scene'] or '?'} ({c['fitted_costs']}, "
                 f"{c['threads']} CPU thread{'s' if c['threads'] != 1 else ''}; {c['rule']})")
    return text


def _format_calibration(cal) -> str:
    if "skipped" in cal:
        return f"calibration skipped: {cal['skipped']}"
    c = cal["costs"]
    text = (f"calibration on {cal['fit_on']}'s measured per-map times: "
            f"{c['per_node'] * 1e9:.2f} ns/node, {c['per_test'] * 1e9:.2f} ns/test, "
            f"{c['per_found'] * 1e9:.2f} ns/found, {c['fixed'] * 1e3:.2f} ms/map; "
            f"R^2 {cal['self']['r2']:.3f} (largest error "
            f"{cal['self']['max_rel_error'] * 100:.0f}%)")
    if "other" in cal:
        text += (f"; predicts {cal['other_scene']} with R^2 {cal['other']['r2']:.3f} "
                 f"(largest error {cal['other']['max_rel_error'] * 100:.0f}%)")
        if "threads_differ" in cal:
            text += f" [{cal['threads_differ']}]"
    if "design" in cal:
        d = cal["design"]
        text += (f"; design: largest VIF {max(d['vif'].values()):.3g}, condition number "
                 f"{d['condition_number']:.3g}")
        weak = [k for k, (low, _) in cal["intervals"].items() if not low > 0]
        if cal.get("zero"):
            text += f"; fitted to 0: {', '.join(cal['zero'])}"
        elif weak:
            text += f"; 95% interval reaches 0: {', '.join(weak)}"
        if cal.get("zero") or weak:
            text += ("; one run does not tell the costs apart ('partpm calibrate' records "
                     "sets that do)")
    return text


def _format_sensitivity(sens, n, first_n) -> str:
    skipped = [f"{r['constant']} x{r['factor']:g}" for r in sens if r.get("skipped")]
    sens = [r for r in sens if not r.get("skipped")]
    speeds = [r["speedup"] for r in sens]
    shares = [r["gather_share"] for r in sens]
    energy = [r["energy_ratio"] for r in sens if r["energy_ratio"] is not None]
    dram = [_mb(r["dram_bytes"]) for r in sens]
    worst = min(sens, key=lambda r: r["speedup"])
    if n == first_n:
        return (f"sensitivity: one n recorded (n = {n}), so no speedup to vary; record "
                f"several (partpm speedup SCENE --maps 1,2,4,...)")
    configured = sens[0]["energy_ratio"]
    energy_text = (f"{min(energy):.2f}-{max(energy):.2f}x (as configured "
                   + (f"{configured:.2f}x)" if configured is not None else
                      f"not defined: a frame at n = {first_n} costs no energy)")
                   if energy else f"not defined (a frame at n = {first_n} costs no energy)")
    return (f"sensitivity (each assumed constant x0.5 and x2): speedup at n = {n} over "
            f"n = {first_n} {min(speeds):.2f}-{max(speeds):.2f} (as configured "
            f"{sens[0]['speedup']:.2f}; lowest with {worst['constant']} "
            f"x{worst['factor']:g}), gather share {min(shares) * 100:.2f}-"
            f"{max(shares) * 100:.2f}%, energy per frame at n = {n} over n = {first_n} "
            f"{energy_text}, DRAM per frame at n = {n} "
            f"{min(dram):.1f}-{max(dram):.1f} MB (as configured {dram[0]:.1f} MB)"
            + (f"; left out, beyond the allowed range: {', '.join(skipped)}" if skipped
               else ""))
