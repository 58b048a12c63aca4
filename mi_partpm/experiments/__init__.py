"""The paper's experiments and the project's measurements, apart from the renderer's core.

- :mod:`.compare`: ``partpm compare``, pm vs partpm vs a path-traced reference (figures 7-12),
  with :mod:`.metrics` and :mod:`.figures`;
- :mod:`.speedup`: ``partpm speedup``, one map's estimate time vs n (figures 5-6), and the
  workloads hwsim replays;
- :mod:`.bench`: ``partpm bench``, the kd-tree and tracer against named baselines;
- :mod:`.scaling` and :mod:`.reducebench`: ``partpm scaling``, the MPI backend over P ranks,
  and the reduction micro-benchmark its gather model is fitted to;
- :mod:`.converge`: ``partpm converge``, error against time of progressive partpm, pm and
  path;
- :mod:`.notebook`: what the notebooks share (sizes, reuse of finished runs);
- :mod:`.regenerate` and :mod:`.readme`: ``partpm figures``, every experiment behind the
  README and the notebooks, reused when the code and settings match, and the README's
  generated tables; :mod:`.provenance`: the code version, commit and machine of a result.
"""
