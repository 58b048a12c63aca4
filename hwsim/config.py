"""The hardware configuration of a simulated PE array, with units, defaults and validation.

Load from TOML (:func:`load_config`) or build in Python; every invalid value raises a
ValueError naming the field, the value and what is allowed. Defaults describe a plausible
FPGA-class design and are assumptions, not measurements (see the sensitivity sweep).

TOML layout (every key optional)::

    pe_count = 32                  # processing elements, >= 1 (for simulate(); the report
                                   # of 'partpm hwsim' sets P itself and refuses this key)
    clock_hz = 200e6               # PE and network clock
    cycles_per_node = 4            # per kd-tree node visited
    cycles_per_test = 3            # per photon distance test
    cycles_per_accumulate = 2      # per photon found (f_r * power added)
    cycles_per_map = 0             # per map run on a PE (its set-up), before its first tile
    outstanding_queries = 4        # queries in flight per PE (hides DRAM latency)
    bytes_per_result = 12          # one partial radiance (RGB float32)
    gather_schedule = "after"      # "after" the queries, or "tiles" overlapped with them
    tile_queries = 4096            # queries per tile: the unit in which a PE overlaps memory
                                   # with compute, and which the "tiles" gather sends

    [pe]                           # where the four compute costs come from
    costs = "assumed"              # "assumed": the cycles_per_* keys above; "fitted": from
                                   # fitted_costs, a file 'partpm calibrate' writes
    fitted_costs = ""              # with "fitted": that file (relative to this TOML file)

    [memory]
    sram_bytes = 2097152           # local SRAM per PE, shared by its maps; what does not fit
                                   # streams from DRAM
    dram_bytes_per_cycle = 16      # DRAM bandwidth per channel
    dram_latency_cycles = 100
    dram_burst_bytes = 64
    dram_channels = 0              # 0: a private channel per PE; k: k channels shared by all PEs

    [gather]
    topology = "tree"              # a network of hwsim.networks: "bus", "tree" or "ring"
    pipelined = true               # adder tree streams results level to level
    hop_latency_cycles = 2
    link_bytes_per_cycle = 8
    adder_latency_cycles = 4

    [energy]                       # picojoules per action; 45 nm figures, assumptions
    pj_per_node = 11               # read an 8-byte node from SRAM, one compare
    pj_per_test = 31               # read a 12-byte position, 3 sub, 3 mul, 2 add, 1 compare
    pj_per_accumulate = 34         # read 16 bytes of power and direction, 3 mul, 3 add
    pj_per_dram_byte = 160         # a byte moved from DRAM
    pj_per_link_byte = 1           # a byte over one hop of the gather network
    pj_per_add = 2.7               # one partial result (3 floats) added in the gather
    static_watts_per_pe = 0.05     # leakage and clock of one PE while the frame lasts

**Assumed or fitted compute costs** (``[pe] costs``). "assumed" runs the model on
``cycles_per_node``, ``cycles_per_test``, ``cycles_per_accumulate`` and ``cycles_per_map``.
"fitted" runs it on the costs :mod:`hwsim.calibrate` fitted to measured CPU times (the file
``fitted_costs``, see :func:`hwsim.calibrate.write_costs`), converted by one rule: **a PE as
fast as one measured CPU thread**. Cycles per node, test and found photon = CPU seconds per
action x the threads that measured them x ``clock_hz`` (the CPU's wall time per action times
its threads is one thread's time per action); cycles per map = CPU seconds per map run x
``clock_hz`` (the host records and launches a map's kernel in one thread). A config that
sets ``costs = "fitted"`` may not also set the ``cycles_per_*`` keys (they would be ignored).
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field, fields, replace

from .networks import TOPOLOGIES

__all__ = ["MemoryConfig", "GatherConfig", "EnergyConfig", "PEConfig", "HardwareConfig",
           "load_config", "TOPOLOGIES", "COST_SOURCES", "CYCLE_KEYS"]

SCHEDULES = ("after", "tiles")
#: Where the PE's compute costs come from (``[pe] costs``).
COST_SOURCES = ("assumed", "fitted")
#: The assumed compute costs, which ``[pe] costs = "fitted"`` replaces.
CYCLE_KEYS = ("cycles_per_node", "cycles_per_test", "cycles_per_accumulate", "cycles_per_map")


#: The largest value of any number of a configuration, and the least of one that must be
#: above 0 (bytes, cycles, hertz, picojoules, watts): beyond them the model's products of
#: counts and costs overflow 64-bit integers or float64 (2^62 bytes of SRAM, a clock of
#: 1e-300 Hz), and no hardware is near them.
LARGEST = 1e15
LEAST_POSITIVE = 1e-6


def _whole_ints(obj):
    """The integer fields of ``obj`` given as whole floats (a TOML ``2e6`` or ``2.0``) or as
    NumPy integers, checked by ``_check_number(integer=True)``, become ints, as the model's
    counts and indices need; NumPy floats become floats."""
    for f in fields(obj):
        value = getattr(obj, f.name)
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            continue
        if f.type == "int" and float(value).is_integer():
            object.__setattr__(obj, f.name, int(value))
        elif f.type == "float" and type(value) is not float:
            object.__setattr__(obj, f.name, float(value))


def _check_number(owner, name, value, low=0.0, low_open=True, integer=False):
    """``value`` must be a real number (an integer where ``integer``) from ``low`` (above it,
    by :data:`LEAST_POSITIVE` or 1 for an integer, where ``low_open``) to :data:`LARGEST`."""
    what = f"{owner}.{name}" if owner else name
    kind = "an integer" if integer else "a number"
    least = (low + (1 if integer else LEAST_POSITIVE)) if low_open else low
    bound = f"in [{least:g}, {LARGEST:g}]"
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or \
            not math.isfinite(value) or (integer and not float(value).is_integer()) or \
            not least <= value <= LARGEST:
        # A NumPy number as Python prints it.
        shown = value.item() if isinstance(value, numbers.Number) and hasattr(value, "item") \
            else value
        raise ValueError(f"{what} must be {kind} {bound}, got {shown!r}")


@dataclass(frozen=True)
class MemoryConfig:
    """A PE's storage levels: local SRAM, shared by the PE's maps, and the DRAM behind it for
    the maps that do not fit (:func:`hwsim.work.sram_resident`)."""

    sram_bytes: int = 2 * 1024 * 1024
    dram_bytes_per_cycle: float = 16.0
    dram_latency_cycles: float = 100.0
    dram_burst_bytes: int = 64
    dram_channels: int = 0

    def __post_init__(self):
        _check_number("memory", "sram_bytes", self.sram_bytes, 0, low_open=False, integer=True)
        _whole_ints(self)
        _check_number("memory", "dram_bytes_per_cycle", self.dram_bytes_per_cycle)
        _check_number("memory", "dram_latency_cycles", self.dram_latency_cycles, 0,
                      low_open=False)
        _check_number("memory", "dram_burst_bytes", self.dram_burst_bytes, integer=True)
        _check_number("memory", "dram_channels", self.dram_channels, 0, low_open=False,
                      integer=True)

    def channels(self, pe_count: int) -> int:
        """How many DRAM channels ``pe_count`` PEs use (PE p on channel p mod channels)."""
        return pe_count if self.dram_channels == 0 else min(self.dram_channels, pe_count)

    def contended(self, pe_count: int) -> bool:
        """Whether some PEs share a DRAM channel."""
        return self.channels(pe_count) < pe_count


@dataclass(frozen=True)
class GatherConfig:
    """The network that sums the PEs' partial results (the gather of eq. 2)."""

    topology: str = "tree"
    pipelined: bool = True
    hop_latency_cycles: float = 2.0
    link_bytes_per_cycle: float = 8.0
    adder_latency_cycles: float = 4.0

    def __post_init__(self):
        if self.topology not in TOPOLOGIES:
            raise ValueError(f"gather.topology must be one of {', '.join(TOPOLOGIES)}, "
                             f"got {self.topology!r}")
        if not isinstance(self.pipelined, bool):
            raise ValueError(f"gather.pipelined must be true or false, got {self.pipelined!r}")
        _check_number("gather", "hop_latency_cycles", self.hop_latency_cycles, 0,
                      low_open=False)
        _check_number("gather", "link_bytes_per_cycle", self.link_bytes_per_cycle)
        _check_number("gather", "adder_latency_cycles", self.adder_latency_cycles, 0,
                      low_open=False)
        _whole_ints(self)


@dataclass(frozen=True)
class EnergyConfig:
    """Energy per action in picojoules, and static power per PE. The defaults follow published
    45 nm figures for float add/multiply, SRAM and DRAM access (Horowitz, ISSCC 2014) summed
    over what one action does; they are assumptions, as the timing constants are."""

    pj_per_node: float = 11.0
    pj_per_test: float = 31.0
    pj_per_accumulate: float = 34.0
    pj_per_dram_byte: float = 160.0
    pj_per_link_byte: float = 1.0
    pj_per_add: float = 2.7
    static_watts_per_pe: float = 0.05

    def __post_init__(self):
        for f in fields(self):
            _check_number("energy", f.name, getattr(self, f.name), 0, low_open=False)
        _whole_ints(self)


@dataclass(frozen=True)
class PEConfig:
    """Where a PE's compute costs come from: ``costs`` "assumed" (the ``cycles_per_*`` of
    :class:`HardwareConfig`) or "fitted" (``fitted_costs``, the file of
    :func:`hwsim.calibrate.write_costs`, read by :func:`load_config` into the ``seconds_*``
    fields and ``threads``: CPU seconds per action as measured with that many threads)."""

    costs: str = "assumed"
    fitted_costs: str = ""
    seconds_per_node: float = 0.0
    seconds_per_test: float = 0.0
    seconds_per_found: float = 0.0
    seconds_per_map: float = 0.0
    threads: int = 1
    fitted_scene: str = ""

    def __post_init__(self):
        if self.costs not in COST_SOURCES:
            raise ValueError(f"pe.costs must be one of {', '.join(COST_SOURCES)}, got "
                             f"{self.costs!r}")
        if not isinstance(self.fitted_costs, str):
            raise ValueError(f"pe.fitted_costs must be a file name (a string), got "
                             f"{self.fitted_costs!r}")
        if self.costs == "fitted" and not self.fitted_costs:
            raise ValueError('pe.costs = "fitted" needs pe.fitted_costs: the costs file '
                             "'partpm calibrate' writes (fitted_costs.toml)")
        if self.costs == "assumed" and self.fitted_costs:
            raise ValueError(f'pe.fitted_costs = {self.fitted_costs!r} is read only with '
                             f'pe.costs = "fitted" (costs = "assumed" runs on the '
                             f"cycles_per_* keys): set costs = \"fitted\" or leave it out")
        seconds = ("seconds_per_node", "seconds_per_test", "seconds_per_found",
                   "seconds_per_map")
        for name in seconds:
            _check_number("pe", name, getattr(self, name), 0, low_open=False)
        _check_number("pe", "threads", self.threads, 1, low_open=False, integer=True)
        _whole_ints(self)
        if self.costs == "fitted" and not any(getattr(self, name) for name in seconds):
            raise ValueError(f'pe.costs = "fitted" with no fitted cost: every seconds_per_* '
                             f"is 0 ({self.fitted_costs} gave no time per action, a fit on "
                             f"too small a workload: calibrate on a larger one or set costs = "
                             f"\"assumed\"; or the costs were not read from it: in Python "
                             f"PEConfig.from_file or load_config reads them)")

    @classmethod
    def from_file(cls, path) -> "PEConfig":
        """Fitted costs from the file of :func:`hwsim.calibrate.write_costs`."""
        from pathlib import Path

        from .calibrate import read_costs
        if not Path(path).is_file():
            raise ValueError(f"pe.fitted_costs: {path} is not a file (write one with 'partpm "
                             f"calibrate SCENE --out DIR': DIR/fitted_costs.toml)")
        c = read_costs(path)
        return cls(costs="fitted", fitted_costs=str(path),
                   seconds_per_node=c["seconds_per_node"],
                   seconds_per_test=c["seconds_per_test"],
                   seconds_per_found=c["seconds_per_found"],
                   seconds_per_map=c["seconds_per_map"], threads=c["threads"],
                   fitted_scene=c["scene"])


@dataclass(frozen=True)
class HardwareConfig:
    """A PE array: every PE holds whole maps and answers every query on them."""

    pe_count: int = 32
    clock_hz: float = 200e6
    cycles_per_node: float = 4.0
    cycles_per_test: float = 3.0
    cycles_per_accumulate: float = 2.0
    cycles_per_map: float = 0.0
    outstanding_queries: int = 4
    bytes_per_result: int = 12
    gather_schedule: str = "after"
    tile_queries: int = 4096
    memory: MemoryConfig = field(default_factory=MemoryConfig)
    gather: GatherConfig = field(default_factory=GatherConfig)
    energy: EnergyConfig = field(default_factory=EnergyConfig)
    pe: PEConfig = field(default_factory=PEConfig)

    def __post_init__(self):
        # The four tables: their config objects, or dicts of their fields (as with_() takes).
        for name, cls in (("memory", MemoryConfig), ("gather", GatherConfig),
                          ("energy", EnergyConfig), ("pe", PEConfig)):
            value = getattr(self, name)
            if isinstance(value, dict):
                value = _pe_from_dict(value, None) if cls is PEConfig and \
                    set(value) <= set(PE_KEYS) else cls(**_from_dict(cls, value, name))
                object.__setattr__(self, name, value)
            elif not isinstance(value, cls):
                raise ValueError(f"{name} must be a dict of its fields or {cls.__name__}(...), "
                                 f"got {value!r:.60}")
        _check_number("", "pe_count", self.pe_count, 1, low_open=False, integer=True)
        _check_number("", "clock_hz", self.clock_hz)
        for name in CYCLE_KEYS:
            _check_number("", name, getattr(self, name), 0, low_open=False)
        if self.pe.costs != "fitted" and not (self.cycles_per_node or self.cycles_per_test
                                              or self.cycles_per_accumulate):
            raise ValueError("cycles_per_node, cycles_per_test and cycles_per_accumulate are "
                             "all 0: a query would take no time; set at least one > 0")
        _check_number("", "outstanding_queries", self.outstanding_queries, 1, low_open=False,
                      integer=True)
        _check_number("", "bytes_per_result", self.bytes_per_result, integer=True)
        if self.gather_schedule not in SCHEDULES:
            raise ValueError(f"gather_schedule must be one of {', '.join(SCHEDULES)}, got "
                             f"{self.gather_schedule!r}")
        _check_number("", "tile_queries", self.tile_queries, 1, low_open=False, integer=True)
        _whole_ints(self)

    def compute_cycles(self) -> dict:
        """The compute costs the model runs on, in cycles: ``{"node", "test", "found",
        "map"}``, and ``"source"``, "assumed" or "fitted" (converted as the module says: a
        PE as fast as one measured CPU thread)."""
        if self.pe.costs == "fitted":
            per_action = self.pe.threads * self.clock_hz
            return {"source": "fitted", "node": self.pe.seconds_per_node * per_action,
                    "test": self.pe.seconds_per_test * per_action,
                    "found": self.pe.seconds_per_found * per_action,
                    "map": self.pe.seconds_per_map * self.clock_hz}
        return {"source": "assumed", "node": self.cycles_per_node,
                "test": self.cycles_per_test, "found": self.cycles_per_accumulate,
                "map": self.cycles_per_map}

    def with_(self, **changes) -> "HardwareConfig":
        """A copy with some fields changed (``memory``/``gather``/``energy``/``pe`` fields as
        dicts)."""
        _from_dict(type(self), changes, "HardwareConfig.with_()")
        for key in ("memory", "gather", "energy", "pe"):
            if isinstance(changes.get(key), dict):
                part = getattr(self, key)
                _from_dict(type(part), changes[key], f"HardwareConfig.with_({key}=...)")
                changes[key] = replace(part, **changes[key])
        return replace(self, **changes)


def _from_dict(cls, data: dict, where: str):
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"unknown key{'s' if len(unknown) > 1 else ''} in {where}: "
                         f"{', '.join(unknown)} (known: {', '.join(sorted(known))})")
    return data


#: The keys of ``[pe]`` a TOML file may set (the rest are read from ``fitted_costs``).
PE_KEYS = ("costs", "fitted_costs")


def _pe_from_dict(data: dict, base) -> PEConfig:
    """``[pe]``: with ``costs = "fitted"``, the costs file read (its name relative to
    ``base``, the TOML file's directory, or the working directory)."""
    from pathlib import Path
    unknown = sorted(set(data) - set(PE_KEYS))
    if unknown:
        raise ValueError(f"unknown key{'s' if len(unknown) > 1 else ''} in [pe]: "
                         f"{', '.join(unknown)} (known: {', '.join(PE_KEYS)})")
    if data.get("costs", "assumed") != "fitted":
        return PEConfig(**data)
    if not isinstance(data.get("fitted_costs"), str) or not data["fitted_costs"]:
        return PEConfig(**data)                  # raises: "fitted" needs a file name
    path = Path(data["fitted_costs"])
    if not path.is_absolute() and base is not None:
        path = Path(base) / path
    return PEConfig.from_file(path)


def load_config(path=None, **overrides) -> HardwareConfig:
    """A :class:`HardwareConfig` from a TOML file (defaults for what it leaves out). With
    ``[pe] costs = "fitted"`` the costs file is read now (its name relative to the TOML
    file), and the ``cycles_per_*`` keys may not be set."""
    from pathlib import Path
    data = {}
    if path is not None:
        import tomllib
        with open(path, "rb") as f:
            try:
                data = tomllib.load(f)
            except tomllib.TOMLDecodeError as e:
                raise ValueError(f"{path} is not valid TOML: {e}") from None
    data.update(overrides)
    tables = {}
    for name, cls in (("memory", MemoryConfig), ("gather", GatherConfig),
                      ("energy", EnergyConfig), ("pe", PEConfig)):
        table = data.pop(name, {})
        if not isinstance(table, dict):
            keys = PE_KEYS if name == "pe" else [f.name for f in fields(cls)]
            raise ValueError(f"{name} must be a table, [{name}] with keys among "
                             f"{', '.join(keys)}, got {name} = {table!r}")
        tables[name] = dict(table)
    memory = _from_dict(MemoryConfig, tables["memory"], "[memory]")
    gather = _from_dict(GatherConfig, tables["gather"], "[gather]")
    energy = _from_dict(EnergyConfig, tables["energy"], "[energy]")
    pe = _pe_from_dict(tables["pe"], Path(path).parent if path else None)
    top = _from_dict(HardwareConfig, data, "the top level")
    if pe.costs == "fitted":
        clash = [k for k in CYCLE_KEYS if k in top]
        if clash:
            raise ValueError(f'[pe] costs = "fitted" takes the compute costs from '
                             f"{pe.fitted_costs}: leave out {', '.join(clash)} (or set "
                             f'costs = "assumed")')
    return HardwareConfig(**top, memory=MemoryConfig(**memory), gather=GatherConfig(**gather),
                          energy=EnergyConfig(**energy), pe=pe)
