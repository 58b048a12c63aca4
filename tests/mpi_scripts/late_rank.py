"""Run under mpiexec -n 2: a render with a time limit and no pass count, where rank 1's
clock runs half a second behind rank 0's (as when one node loads the scene later). Every
rank must stop after the same pass; one that went on would wait in the gather for ever."""
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")
import mi_partpm  # noqa: E402
from mpi4py import MPI  # noqa: E402

scene = mi_partpm.load_scene("cornell_box", resolution=(16, 16), spp=1)
integrator = mi.load_dict({"type": "partpm", "photon_count": 2000, "map_count": 2,
                           "time_limit": 1.0, "backend": "mpi"})
if MPI.COMM_WORLD.rank == 1:
    after_pass = integrator._after_pass

    def late(pass_index, terms, start, image):
        return after_pass(pass_index, terms, start + 0.5, image)
    integrator._after_pass = late
mi.render(scene, integrator=integrator)
passes = MPI.COMM_WORLD.gather(integrator.stats["passes"], root=0)
if MPI.COMM_WORLD.rank == 0:        # one line from one process: ranks' prints interleave
    print("passes per rank:", *passes, flush=True)
