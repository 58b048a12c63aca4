"""Run under mpiexec -n 2: a progressive render of 50 passes in which only rank 1 is asked
to stop (as by a Ctrl-C sent to that rank alone), after its third pass. Every rank must
stop after that same pass: one that went on would wait in the gather for ever, and a stop
that only rank 0 may ask for would be ignored."""
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")
import mi_partpm  # noqa: E402
from mpi4py import MPI  # noqa: E402

scene = mi_partpm.load_scene("cornell_box", resolution=(16, 16), spp=1)
integrator = mi.load_dict({"type": "partpm", "photon_count": 2000, "map_count": 2,
                           "passes": 50, "backend": "mpi"})
if MPI.COMM_WORLD.rank == 1:
    asked = []

    def stop_requested():
        asked.append(1)
        return len(asked) >= 3
    integrator.stop_requested = stop_requested
mi.render(scene, integrator=integrator)
passes = MPI.COMM_WORLD.gather(integrator.stats["passes"], root=0)
if MPI.COMM_WORLD.rank == 0:        # one line from one process: ranks' prints interleave
    print("passes per rank:", *passes, flush=True)
