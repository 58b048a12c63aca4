"""hwsim: a trace-driven simulator of a processing-element array running partitioned photon
maps (one or more maps per PE, joined by a gather network).

It reads the workloads that ``partpm speedup`` records (:mod:`hwsim.workload`, format in
``WORKLOAD.md``) and a hardware configuration (:mod:`hwsim.config`, TOML or dataclass), and
computes a frame's critical path analytically (:mod:`hwsim.model`). It never imports Mitsuba.
"""
