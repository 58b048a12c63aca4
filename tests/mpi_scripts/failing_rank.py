"""Run under mpiexec -n 2: rank 1 fails while building its maps; the job must abort with
rank 1's message instead of leaving rank 0 waiting in the reduction. The argument says how
it fails: "error" (an exception, the default), "exit" (sys.exit(3) in the callback) or
"interrupt" (KeyboardInterrupt)."""
import sys

import mitsuba as mi

mi.set_variant("llvm_ad_rgb")
import mi_partpm  # noqa: E402
from mpi4py import MPI  # noqa: E402

how = sys.argv[1] if len(sys.argv) > 1 else "error"
scene = mi_partpm.load_scene("cornell_box", resolution=(16, 16), spp=1)
integrator = mi.load_dict({"type": "partpm", "photon_count": 2000, "map_count": 2,
                           "backend": "mpi"})
if MPI.COMM_WORLD.rank == 1:
    def broken(scene, *args):
        if how == "exit":
            sys.exit(3)
        if how == "interrupt":
            raise KeyboardInterrupt
        raise MemoryError("cannot allocate the photon map (simulated)")
    integrator.build_maps = broken
mi.render(scene, integrator=integrator)
print("rank", MPI.COMM_WORLD.rank, "finished")
