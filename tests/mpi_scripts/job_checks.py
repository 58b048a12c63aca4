"""Run under mpiexec -n 2 with one case as argument (the tests of test_mpi.py read the
lines it prints on rank 0):

- ``seed``: rank 1 renders with another seed than rank 0 (a user's ``seed=comm.rank``):
  their eye paths would differ, and the job must refuse it instead of adding them up;
- ``film``: rank 1 renders a film of another size;
- ``light``: rank 1's scene has a light 4 times brighter (another copy of a scene file);
- ``cancel``: both ranks' ``on_pass`` call ``cancel()`` after the third pass of 50: every
  rank must stop after that pass, as a local render does;
- ``totals``: the stats of a render with caustic maps, whose top level must be the whole
  job's (photons and segments summed over the ranks, times the slowest rank's).
"""
import json
import sys

import mitsuba as mi

mi.set_variant("llvm_ad_rgb")
import mi_partpm  # noqa: E402
from mpi4py import MPI  # noqa: E402

case = sys.argv[1]
rank = MPI.COMM_WORLD.rank
size = (16, 16) if case != "film" or rank == 0 else (16, 12)
scene = mi_partpm.load_scene("caustic_glass" if case == "totals" else "cornell_box",
                             resolution=size, spp=1)
props = {"type": "partpm", "photon_count": 4000, "map_count": 4, "backend": "mpi"}
if case == "cancel":
    props["passes"] = 50
if case == "totals":
    props.update(caustic_photon_count=4000, passes=2)
if case == "light" and rank == 1:
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("emitter.radiance.value"))
    params[key] = params[key] * 4
    params.update()
integrator = mi.load_dict(props)
if case == "cancel":
    def on_pass(info):
        if info["pass"] == 3:
            integrator.cancel()
    integrator.on_pass = on_pass
mi.render(scene, integrator=integrator, seed=rank if case == "seed" else 0)
stats = integrator.stats
passes = MPI.COMM_WORLD.gather(stats["passes"], root=0)
if rank == 0:        # one line from one process: ranks' prints interleave
    print("passes per rank:", *passes, flush=True)
    print("stats:", json.dumps({k: v for k, v in stats.items()
                                if isinstance(v, (int, float, list))}), flush=True)
    print("ranks:", json.dumps(stats["ranks"]), flush=True)
