"""Run under mpiexec -n 2: a render whose eye samples are split into sets
(``samples_per_pass``) on the MPI backend, and on rank 0 the same render locally; rank 0
prints the largest difference relative to the image's largest value and the photons traced
(read by test_mpi.py)."""
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")
import numpy as np  # noqa: E402

import mi_partpm  # noqa: E402
from mpi4py import MPI  # noqa: E402

scene = mi_partpm.load_scene("cornell_box_diffuse", resolution=(24, 24), spp=4)
props = {"type": "partpm", "photon_count": 20_000, "map_count": 4, "samples_per_pass": 2}
integrator = mi.load_dict({**props, "backend": "mpi"})
image = np.array(mi.render(scene, integrator=integrator, seed=1))
if MPI.COMM_WORLD.rank == 0:
    local = np.array(mi.render(mi_partpm.load_scene("cornell_box_diffuse", resolution=(24, 24),
                                                    spp=4),
                               integrator=mi.load_dict(props), seed=1))
    print("relative difference:", float(np.abs(image - local).max() / local.max()), flush=True)
    print("photons traced:", integrator.stats["photons_traced"], flush=True)
