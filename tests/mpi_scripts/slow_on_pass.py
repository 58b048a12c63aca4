"""Run under mpiexec -n 2: a render with a time limit and no pass count, where rank 0's
on_pass takes 0.3 s (as writing a checkpoint does). Time in on_pass is not counted, so the
job stops by rank 0's clock and every rank says so: rank 1, which waited for rank 0 and
counted the wait, stopped the job early and made rank 0 say "another_process"."""
import time

import mitsuba as mi

mi.set_variant("llvm_ad_rgb")
import mi_partpm  # noqa: E402
from mpi4py import MPI  # noqa: E402

scene = mi_partpm.load_scene("cornell_box", resolution=(16, 16), spp=1)
integrator = mi.load_dict({"type": "partpm", "photon_count": 2000, "map_count": 2,
                           "time_limit": 1.5, "backend": "mpi"})
if MPI.COMM_WORLD.rank == 0:
    integrator.on_pass = lambda info: time.sleep(0.3)
mi.render(scene, integrator=integrator)
stopped = MPI.COMM_WORLD.gather(integrator.stats.get("stopped_by"), root=0)
if MPI.COMM_WORLD.rank == 0:        # one line from one process: ranks' prints interleave
    print("stopped by:", *stopped, flush=True)
