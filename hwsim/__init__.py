"""hwsim: a trace-driven simulator of a processing-element array running partitioned photon
maps (one map per PE, joined by a gather network). It reads workload files and a hardware
configuration and never imports Mitsuba. The simulator itself is not written yet."""
