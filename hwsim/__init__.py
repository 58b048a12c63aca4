"""hwsim: a trace-driven simulator of a processing-element array running partitioned photon
maps (one or more maps per PE, joined by a gather network).

It reads the workloads that ``partpm speedup`` records (:mod:`hwsim.workload`, format in
``WORKLOAD.md``) and a hardware configuration (:mod:`hwsim.config`, TOML or dataclass), and
computes a frame's critical path analytically (:mod:`hwsim.model`), or event by event where
PEs contend for shared DRAM channels (:mod:`hwsim.events`). :mod:`hwsim.calibrate` fits its
costs to measured CPU times (the calibration sets of ``partpm calibrate``), which the model
runs on with ``[pe] costs = "fitted"``; :mod:`hwsim.collective` fits the MPI reduction's
alpha-beta(-gamma) cost; :mod:`hwsim.report` writes the reports. It never imports Mitsuba.
The layout: docs/architecture.md.
"""
