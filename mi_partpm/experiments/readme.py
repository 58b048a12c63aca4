"""The README's generated blocks: one formatter per block, and the rewrite of the blocks.

A generated block of ``README.md`` sits between two markers on lines of their own::

    <!-- generated: NAME -->
    ...
    <!-- end generated: NAME -->

:data:`BLOCKS` names every block, the steps of ``partpm figures``
(:mod:`.regenerate`) whose results it is made from, and the function that formats them as
markdown (a table, sometimes with a line or an image after it). :func:`replace_blocks` puts
new contents between the markers of the blocks it is given and leaves the rest of the file,
other blocks included, as it was. :func:`note` is the line every block ends with: the
commands, the commit, the date and the machine that made it.

Formatters read only result files (``metrics.json``, ``speedup.json``, ``report.json``, ...),
never the renderer, so they run in a second and can be tested on hand-made results.
"""
from __future__ import annotations

import re
import statistics
from dataclasses import dataclass
from typing import Callable, Dict, Sequence, Tuple

__all__ = ["BLOCKS", "Block", "BlockError", "begin_marker", "end_marker", "block_names",
           "replace_blocks", "note", "machine_summary"]


def begin_marker(name: str) -> str:
    return f"<!-- generated: {name} -->"


def end_marker(name: str) -> str:
    return f"<!-- end generated: {name} -->"


class BlockError(ValueError):
    """A block's markers are missing, duplicated or out of order."""


_MARKER = re.compile(r"^([ \t]*)<!-- (end )?generated: ([A-Za-z0-9_.-]+) -->[ \t]*$",
                     re.MULTILINE)


def block_names(text: str) -> list:
    """The names of the blocks ``text`` opens, in order."""
    return [m.group(3) for m in _MARKER.finditer(text) if not m.group(2)]


def _span(text: str, name: str) -> Tuple[int, int, str]:
    """(end of the begin marker's line, start of the end marker's line, the begin marker's
    indentation) of block ``name``."""
    begins = [m for m in _MARKER.finditer(text) if not m.group(2) and m.group(3) == name]
    ends = [m for m in _MARKER.finditer(text) if m.group(2) and m.group(3) == name]
    for kind, found, marker in (("begin", begins, begin_marker(name)),
                                ("end", ends, end_marker(name))):
        if not found:
            raise BlockError(f"the {kind} marker of block {name!r} is missing: add a line "
                             f"'{marker}'")
        if len(found) > 1:
            raise BlockError(f"the {kind} marker of block {name!r} appears {len(found)} times "
                             f"(lines {', '.join(str(_line(text, m.start())) for m in found)})")
    begin, end = begins[0], ends[0]
    if end.start() < begin.end():
        raise BlockError(f"block {name!r} ends (line {_line(text, end.start())}) before it "
                         f"begins (line {_line(text, begin.start())})")
    inner = [m for m in _MARKER.finditer(text, begin.end(), end.start())]
    if inner:
        raise BlockError(f"block {name!r} holds the marker of block {inner[0].group(3)!r} "
                         f"(line {_line(text, inner[0].start())}): blocks do not nest")
    return begin.end(), end.start(), begin.group(1)


def _line(text: str, offset: int) -> int:
    return text.count("\n", 0, offset) + 1


def replace_blocks(text: str, contents: Dict[str, str]) -> str:
    """``text`` with the lines between the markers of each block in ``contents`` replaced by
    its content; every other line, and every block not in ``contents``, unchanged. Raises
    :class:`BlockError` (before changing anything) when a block's markers are missing,
    duplicated, out of order or nested. A block whose begin marker is indented (inside a
    list item) gets its lines indented the same."""
    spans = {name: _span(text, name) for name in contents}
    for name, (start, end, indent) in sorted(spans.items(), key=lambda kv: -kv[1][0]):
        body = "\n".join(indent + line if line.strip() else ""
                         for line in contents[name].strip("\n").splitlines())
        text = text[:start] + "\n" + (body + "\n" if body else "") + text[end:]
    return text


# ----------------------------------------------------------------------------- formatting

def _pct(share: float) -> str:
    """A share as a percentage: 0%, 0.47%, 13.6%."""
    p = share * 100
    if p == 0:
        return "0%"
    return f"{p:.2f}%" if p < 10 else f"{p:.1f}%"


def _table(header: Sequence[str], align: Sequence[str], rows) -> str:
    lines = ["| " + " | ".join(header) + " |",
             "| " + " | ".join("---:" if a == "r" else "---" for a in align) + " |"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def _or_dash(value, fmt: str) -> str:
    return "-" if value is None or value != value else format(value, fmt)


#: Short names of the scenes in tables that put two scenes side by side.
SHORT = {"cornell_box": "Cornell", "happy_buddha": "Buddha"}

#: How the pairs of the comparison are named in the tables.
PAIR_LABELS = {"partpm_vs_pm": "partpm vs pm", "pm_vs_reference": "pm vs path",
               "partpm_vs_reference": "partpm vs path",
               "partpm_best_vs_reference": "partpm, best configuration, vs path"}


def _pair_label(name: str) -> str:
    return PAIR_LABELS.get(name, name.replace("_vs_reference", " vs path")
                           .replace("_vs_", " vs ").replace("_", " "))


def _metric_cells(m: dict) -> list:
    return [f"{m['rel_mse']:.4f}", f"{m['mare']:.3f}", f"{m['ssim']:.3f}",
            f"{m['mean_ratio']:.3f}", f"{m['max_block_error_share']:.3f}"]


def format_compare(results: dict, scenes=("cornell_box", "happy_buddha")) -> str:
    """The comparison table of the paper's configuration (``metrics.json`` per scene)."""
    rows = []
    for scene in scenes:
        r = results[f"compare_{scene}"]
        k = r["settings"]["k"]
        knn = r.get("mean_knn_radius")
        head = [scene, f"{k} ({_or_dash(knn, '#.3g')} / {r['radius']:.3g})"]
        for i, pair in enumerate(("partpm_vs_pm", "pm_vs_reference", "partpm_vs_reference")):
            rows.append((head if i == 0 else ["", ""]) + [_pair_label(pair)]
                        + _metric_cells(r["metrics"][pair]))
    return _table(["scene", "k (mean kNN radius / r)", "pair", "relMSE", "MARE", "SSIM",
                   "mean ratio", "largest 8x8 share"], "lllrrrrr", rows)


def _best_desc(desc: dict) -> str:
    skip = ("type", "seed", "map_count", "radius_fraction")
    return ", ".join(f"`{k}={v}`" for k, v in desc.items() if k not in skip)


def format_compare_best(results: dict, scenes=("cornell_box", "happy_buddha",
                                               "glossy_spheres"), images: str = "") -> str:
    """Every method against path per scene, the best configuration's rows included when it
    was rendered, and how much of partpm's error (both configurations) sits in the tile
    where partpm and pm differ most (``worst_tile`` of ``metrics.json``)."""
    rows, best = [], None
    for scene in scenes:
        r = results[f"compare_{scene}"]
        tile = r.get("worst_tile") or {}
        in_tile = {"partpm_vs_reference": tile.get("share"),
                   "partpm_best_vs_reference": tile.get("share_other")}
        pairs = [p for p in r["metrics"] if p.endswith("_vs_reference")]
        for i, pair in enumerate(pairs):
            rows.append([scene if i == 0 else "", _pair_label(pair)]
                        + _metric_cells(r["metrics"][pair]) + [_or_dash(in_tile.get(pair),
                                                                        ".3f")])
        best = best or r.get("best")
    text = _table(["scene", "pair", "relMSE", "MARE", "SSIM", "mean ratio",
                   "largest 8x8 share", "share in the partpm - pm tile"], "llrrrrrr", rows)
    if best:
        text += (f"\n\nBest configuration, at the same photon budget: {_best_desc(best)} "
                 f"(`BEST` in `mi_partpm/experiments/compare.py`). The last column is the "
                 f"share of the image's squared error against path that lies in the 8x8 "
                 f"tile where partpm (the paper's configuration) and pm differ most.")
    if images and "compare_glossy_spheres" in results:
        text += (f"\n\n![Glossy spheres: pm, partpm, its best configuration, path, and their "
                 f"differences]({images}compare_glossy_spheres.png)")
    return text


def format_speedup(results: dict, scenes=("cornell_box", "happy_buddha")) -> str:
    """The speedup table (``speedup.json`` per scene)."""
    rows = []
    for scene in scenes:
        for i, r in enumerate(results[f"speedup_{scene}"]["rows"]):
            rows.append([scene if i == 0 else "", r["n"], f"{r['per_map_seconds'] * 1e3:.0f}",
                         f"{r['speedup']:.2f}", f"{r['total_seconds']:.2f}",
                         f"{r['mean_nodes_visited']:.1f}", f"{r['mean_photons_tested']:.1f}",
                         f"{r['mean_photons_found']:.1f}", r["tree_depth"]])
    return _table(["scene", "n", "one map (ms)", "speedup", "all n maps in turn (s)",
                   "nodes / query", "photons tested / query", "photons found / query",
                   "tree depth"], "lrrrrrrrr", rows)


def _value(v: float) -> str:
    return f"{v:,.0f}" if abs(v) >= 1000 else f"{v:.3g}"


def format_bench(results: dict) -> str:
    """Every row of ``partpm bench`` (``bench.json``)."""
    rows = []
    for r in results["bench"]["rows"]:
        unit = r["unit"]
        meaning = r["ratio_meaning"]
        if r["ratio"] == r["ours"]:          # the row's own figure, held to the target
            ratio = ""
        elif meaning == "baseline time / ours":
            ratio = f"{r['ratio']:.2f}x faster" if r["ratio"] >= 1 else f"{r['ratio']:.2f}x"
        elif "rate" in meaning or "/s" in meaning:
            ratio = f"{r['ratio']:.2f}x"
        else:
            ratio = f"{r['ratio']:.2f}"
        if ratio and r.get("ratio_range"):
            lo, hi = r["ratio_range"]
            ratio += f" ({lo:.2f}-{hi:.2f})"
        target = ("-" if r["target"] is None else f"{r['target']:g}x"
                  if r["target_is"] == "at least" else f"<= {r['target']:g}")
        met = "-" if r["met"] is None else "yes" if r["met"] else "no"
        rows.append([r["benchmark"], f"{_value(r['ours'])} {unit}",
                     f"{r['baseline_name']}: {_value(r['baseline'])} {unit}", ratio, target,
                     met])
    return _table(["benchmark", "ours", "baseline", "ratio", "target", "met"], "lrrrrl", rows)


def _pick(ns, wanted) -> list:
    """The n of ``wanted`` that were recorded, and the largest recorded n."""
    ns = sorted(ns)
    return sorted({n for n in ns if n in wanted} | {ns[-1]})


def format_hwsim(results: dict, scenes=("cornell_box", "happy_buddha"),
                 show=(1, 8, 32)) -> str:
    """hwsim with one PE per map at the paper's size (``report.json`` per scene)."""
    rows = []
    for scene in scenes:
        report = results[f"hwsim_{scene}"]["rows"]
        picked = _pick([r["n"] for r in report], show)
        for i, r in enumerate(x for x in report if x["n"] in picked):
            rows.append([scene if i == 0 else "", r["n"], f"{r['seconds'] * 1e3:.0f}",
                         f"{r['speedup']:.2f}", f"{r['speedup_without_gather']:.2f}",
                         _pct(r["gather_share"]), f"{r['load_imbalance']:.2f}"])
    return _table(["scene", "n = PEs", "frame (ms)", "speedup", "without gather",
                   "gather share", "load imbalance"], "lrrrrrr", rows)


def format_hwsim_wide(results: dict, scenes=("cornell_box", "happy_buddha"),
                      show=(1, 8, 32, 128, 1024)) -> str:
    """hwsim up to the largest n of the wide runs, the scenes side by side."""
    reports = [{r["n"]: r for r in results[f"hwsim_wide_{scene}"]["rows"]} for scene in scenes]
    common = set.intersection(*(set(r) for r in reports))
    header, rows = ["n = PEs"], []
    for scene in scenes:
        short = SHORT.get(scene, scene)
        header += [f"{short} speedup", "gather share", "efficiency", "nodes x", "energy (mJ)"]
    for n in _pick(common, show):
        row = [n]
        for report in reports:
            r = report[n]
            row += [f"{r['speedup']:.2f}", _pct(r["gather_share"]), f"{r['efficiency']:.2f}",
                    _or_dash(r["replicated_traversal"], ".2f"), f"{r['energy_mj']:.1f}"]
        rows.append(row)
    return _table(header, "r" * len(header), rows)


#: The gather networks of hwsim's sweep in the order and words of the README.
NETWORK_LABELS = {"tree": "tree, pipelined", "ring": "ring, pipelined",
                  "tree s&f": "tree, store-and-forward", "ring s&f": "ring, store-and-forward",
                  "bus": "bus"}


def format_hwsim_networks(results: dict, scenes=("cornell_box", "happy_buddha"),
                          show=(32, 256, 1024)) -> str:
    """The gather's share of the frame per gather network, n = P (``networks`` of the wide
    runs' ``report.json``), the scenes' shares side by side."""
    tables = [results[f"hwsim_wide_{scene}"] for scene in scenes]
    by = [{(r["gather"], r["n"]): r for r in t["networks"]} for t in tables]
    ns = sorted(set.intersection(*({r["n"] for r in t["networks"]} for t in tables)))
    cols = [n for n in show if n in ns] or [n for n in ns if n > 1][-3:] or ns[-1:]
    gather = tables[0]["config"]["gather"]
    same = {r["gather"]: r["pipelined"] for r in tables[0]["networks"]
            if r["topology"] == gather["topology"]}
    default = next((g for g, p in same.items() if p == gather["pipelined"]),
                   next(iter(same), None))
    labels = [g for g in NETWORK_LABELS if any(g == r["gather"] for r in tables[0]["networks"])]
    labels += [g for g in dict.fromkeys(r["gather"] for r in tables[0]["networks"])
               if g not in labels]
    rows = []
    for g in labels:
        name = NETWORK_LABELS.get(g, g) + (" (default)" if g == default else "")
        rows.append([name] + [" / ".join(_pct(b[g, n]["gather_share"]) for b in by)
                              for n in cols])
    return _table(["gather network"] + [f"n = {n}" for n in cols], "l" + "r" * len(cols),
                  rows)


def format_mpi_prediction(results: dict, step: str = "scaling_cornell_box") -> str:
    """The reduction and render times of ``partpm scaling`` against their prediction."""
    rows = []
    for r in results[step]:
        if "time_render_pred" not in r:
            continue
        rows.append([r["ranks"], f"{r['time_reduce'] * 1e3:.2f} ms",
                     f"{r['time_reduce_pred_transport'] * 1e3:.2f} ms",
                     f"{r['time_reduce_pred_in_situ'] * 1e3:.2f} ms",
                     f"{r['time_render']:.2f} s",
                     f"{r['time_render_pred']:.2f} s ({r['render_pred_rel_error'] * 100:+.1f}%)",
                     "yes" if r.get("render_pred_out_of_sample") else "no (the model's input)"])
    return _table(["P", "reduce measured", "predicted, transport",
                   "predicted, beside Dr.Jit's threads", "render measured",
                   "render predicted from P = 1", "out of sample"], "rrrrrrl", rows)


def format_scaling(results: dict, step: str = "scaling_cornell_box") -> str:
    """``partpm scaling``: time, speedup and the phases per P (``scaling.json``)."""
    rows = [[r["ranks"], f"{r['time_render']:.2f}", f"{r['speedup']:.2f}",
             f"{r['efficiency']:.2f}", f"{r['time_trace_max']:.2f}",
             f"{r['time_build_max']:.2f}", f"{r['time_estimate_max']:.2f}",
             f"{r['time_reduce'] * 1e3:.1f}", f"{r['reduce_bytes_per_rank'] / 1e3:.0f}",
             f"{r['max_rel_diff_vs_first']:.1e}"]
            for r in results[step]]
    return _table(["P", "render s", "speedup", "efficiency", "trace s", "build s",
                   "estimate s", "reduce ms", "reduce KB per rank",
                   "image vs P = 1, largest relative difference"], "lrrrrrrrrr", rows)


#: The methods of ``partpm converge`` as the table names them.
METHOD_LABELS = {"partpm": "partpm, progressive", "pm": "pm, more photons",
                 "path": "path, more samples"}


def _converge_label(method: str, settings: dict) -> str:
    """A method's name in the table, with the props its run gave it."""
    from .converge import settings_text
    props = {} if method == "path" else dict(settings.get("props", {}))
    if method == "partpm":
        props.update(settings.get("partpm_props", {}))
    return ", ".join(t for t in (METHOD_LABELS.get(method, method), settings_text(props)) if t)


def format_converge(results: dict, scenes=("cornell_box", "caustic_glass",
                                           "cornell_box_diffuse"),
                    images: str = "") -> str:
    """relMSE against path of every method at the times ``converge.json`` interpolates
    (5 s and the time limit), per scene: its run, then its run with other props
    (``converge_<scene>_nee``) where there is one."""
    from .converge import ended_text
    runs = [results[f"converge_{scene}"] for scene in scenes]
    times = sorted({float(t) for r in runs for t in r["at"]})
    rows, ended = [], []
    for scene, run in zip(scenes, runs):
        first = True
        for each in (run, results.get(f"converge_{scene}_nee")):
            if each is None:
                continue
            at = {float(t): v for t, v in each["at"].items()}
            for method in each["settings"]["methods"]:
                label = _converge_label(method, each["settings"])
                rows.append([scene if first else "", label]
                            + [_or_dash(at.get(t, {}).get(method), ".3g") for t in times])
                first = False
                if method in each.get("ends", {}):
                    ended.append(f"{label} on {scene} at {each['ends'][method]:.1f} s "
                                 f"({ended_text(each, method)})")
    s = runs[0]["settings"]
    text = _table(["scene", "method"] + [f"relMSE at {t:g} s" for t in times],
                  "ll" + "r" * len(times), rows)
    text += (f"\n\n{s['resolution'][0]} x {s['resolution'][1]}; relMSE against Mitsuba's "
             f"`path` at {s['reference_spp']} spp; partpm: {s['photons']:,} photons in "
             f"{s['maps']} maps and {s['spp']} spp per pass, alpha = {s['alpha']}; pm: "
             f"k = {s['k']}.")
    noise = [(scene, run.get("reference_rel_mse")) for scene, run in zip(scenes, runs)]
    if all(v is not None for _, v in noise):
        text += (" The references' own noise, estimated from their halves: relMSE about "
                 + ", ".join(f"{v:.2g} ({scene})" for scene, v in noise) + ".")
    if ended:
        text += " A curve ended before the time limit: " + "; ".join(ended) + "."
    if images:
        text += "\n\n" + " ".join(
            f"![error against time, {scene}]({images}converge_{scene}.png)" for scene in scenes)
    return text


def _passes(run: dict) -> dict:
    """passes -> relMSE of partpm in a converge run."""
    out = {}
    for r in run["rows"]:
        if r["method"] == "partpm" and r["setting"].endswith(" passes"):
            out[int(r["setting"].split()[0])] = r["rel_mse"]
    return out


def format_converge_long(results: dict, step: str = "converge_cornell_box_long",
                         early: int = 4, late: int = 64, images: str = "") -> str:
    """The long progressive run: relMSE after ``early`` and ``late`` passes, and their
    ratio (consistency: the error keeps falling as passes accumulate)."""
    run = results[step]
    s, errors = run["settings"], _passes(run)
    e1, e2 = errors.get(early), errors.get(late)
    ratio = f"{e1 / e2:.2f}" if e1 and e2 else "-"
    rows = [[s["scene"], f"{s['seconds']:g} s", max(errors) if errors else 0,
             _or_dash(e1, ".3g"), _or_dash(e2, ".3g"), ratio]]
    text = _table(["scene", "time limit", "passes", f"relMSE after {early} passes",
                   f"relMSE after {late} passes", f"ratio ({early} / {late})"], "lrrrrr", rows)
    if images:
        text += (f"\n\n![partpm, progressive, {s['scene']}: error against time over "
                 f"{s['seconds']:g} s]({images}{step}.png)")
    return text


@dataclass(frozen=True)
class Block:
    """A generated block: the steps it is made from and its formatter
    ``format(results, **kwargs)``, ``results`` mapping step name -> its result file's JSON.
    ``images``: the formatter takes ``images=`` (the prefix of the README's image paths).
    ``cited``: the steps whose commands the block's note names (default: all of ``steps``;
    fewer when some are read only for labels)."""

    name: str
    steps: Tuple[str, ...]
    format: Callable[..., str]
    images: bool = False
    cited: Tuple[str, ...] = ()

    @property
    def note_steps(self) -> Tuple[str, ...]:
        return self.cited or self.steps


def format_calibrate(results: dict, step: str = "calibrate") -> str:
    """``partpm calibrate``'s costs and cross-scene check (its own table)."""
    from .calibrate import format_readme_table
    return format_readme_table(results[step])


#: Renders of each large size: the README's row is their median phase times.
LARGE_RUNS = {"1e7": 3, "1e8": 1}


def large_steps() -> Dict[str, Tuple[str, ...]]:
    """Per large size, the step names of its renders: ``large_SIZE``, then
    ``large_SIZE_runK``."""
    return {size: tuple(f"large_{size}" + (f"_run{k + 1}" if k else "") for k in range(runs))
            for size, runs in LARGE_RUNS.items()}


def format_large(results: dict) -> str:
    """Large renders in waves (``partpm render --stats-json``): photons, waves, phase times
    and the measured peak memory per stored photon. A size rendered several times shows the
    median of each phase's times and the largest peak."""
    rows = []
    for names in large_steps().values():
        rs = [results[name] for name in names]
        r = rs[0]
        stored = max(int(r["photons_stored"]), 1)
        t = {k: float(statistics.median(x[k] for x in rs))
             for k in ("time_trace", "time_build", "time_estimate", "time_render")}
        peak = max(int(x["peak_memory_bytes"]) for x in rs)
        rows.append([f"{int(r['photons_emitted']):,}", f"{int(r['map_count'])}",
                     f"{int(r.get('waves', 1))}", f"{stored:,}", f"{len(rs)}",
                     f"{t['time_trace']:.1f}", f"{t['time_build']:.1f}",
                     f"{t['time_estimate']:.1f}", f"{t['time_render']:.0f}",
                     f"{peak / 1e9:.2f}", f"{peak / stored:.1f}"])
    return _table(["photons emitted", "maps", "waves", "photons stored", "renders",
                   "trace s", "build s", "estimate s", "render s", "peak memory GB",
                   "peak bytes per stored photon"], "rrrrrrrrrrr", rows)


BLOCKS = {b.name: b for b in (
    Block("compare", ("compare_cornell_box", "compare_happy_buddha"), format_compare),
    Block("compare_best", ("compare_cornell_box", "compare_happy_buddha",
                           "compare_glossy_spheres"), format_compare_best, images=True),
    Block("converge", ("converge_cornell_box", "converge_cornell_box_nee",
                       "converge_caustic_glass", "converge_cornell_box_diffuse",
                       "converge_cornell_box_diffuse_nee"), format_converge, images=True),
    Block("converge_long", ("converge_cornell_box_long",), format_converge_long, images=True),
    Block("speedup", ("speedup_cornell_box", "speedup_happy_buddha"), format_speedup),
    Block("bench", ("bench",), format_bench),
    Block("hwsim", ("hwsim_cornell_box", "hwsim_happy_buddha"), format_hwsim),
    Block("hwsim_wide", ("hwsim_wide_cornell_box", "hwsim_wide_happy_buddha"),
          format_hwsim_wide),
    Block("hwsim_networks", ("hwsim_wide_cornell_box", "hwsim_wide_happy_buddha"),
          format_hwsim_networks),
    Block("calibration", ("calibrate",), format_calibrate),
    Block("mpi_prediction", ("scaling_cornell_box",), format_mpi_prediction),
    Block("scaling", ("scaling_cornell_box",), format_scaling),
    Block("large", sum(large_steps().values(), ()), format_large,
          cited=tuple(names[0] for names in large_steps().values())),
)}


def machine_summary(m: dict) -> str:
    """'2 cores, AMD EPYC 7B13, 23.4 GiB' from :func:`.provenance.machine`."""
    parts = []
    if m.get("cores"):
        parts.append(f"{m['cores']} cores")
    cpu = m.get("model") or m.get("processor")
    if cpu:
        parts.append(cpu)
    if m.get("memory_bytes"):
        parts.append(f"{m['memory_bytes'] / 2 ** 30:.1f} GiB")
    return ", ".join(parts) or "unknown machine"


def note(commands: Sequence[str], commits: Sequence[str], dates: Sequence[str],
         machines: Sequence[str], made_by: str = "make figures") -> str:
    """The italic line a block ends with: what made it, from which commands, at which
    commit, when and where (duplicates listed once)."""
    def unique(values):
        return list(dict.fromkeys(v for v in values if v))
    cmds = ", ".join(f"`{c}`" for c in unique(commands))
    commit = ", ".join(unique(commits)) or "unknown"
    days = sorted(unique(d[:10] for d in dates))
    when = days[0] if len(days) == 1 else (f"{days[0]} to {days[-1]}" if days else "unknown")
    return (f"*Generated by `{made_by}` from {cmds}; commit {commit}, {when}; "
            f"{'; '.join(unique(machines)) or 'unknown machine'}.*")
