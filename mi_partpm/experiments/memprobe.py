"""Measure a render's memory in a fresh process: its peak resident memory and Dr.Jit's own.

``python -m mi_partpm.experiments.memprobe --scene S --photons N --out F.json`` renders scene
S at 64 x 64, 1 spp, with N photons emitted into 8 maps, after a small warm-up render, and
writes the number of photons stored, the process's peak resident memory (``ru_maxrss``), the
resident memory before the render and Dr.Jit's peak allocation (its malloc watermark). A fresh
process, so that nothing earlier in the caller counts. :func:`probe` runs it and reads the
result.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

__all__ = ["probe", "measure"]


def _rss_now() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def measure(scene_name: str, photons: int, maps: int = 8, resolution: int = 64,
            variant: str = "llvm_ad_rgb") -> dict:
    """Render in this process (see the module's text) in ``variant`` and return the figures
    (Dr.Jit's peak: of the variant's backend)."""
    import drjit as dr
    import mitsuba as mi
    mi.set_variant(variant)
    import mi_partpm
    from mi_partpm.memory import peak_rss_bytes
    scene = mi_partpm.load_scene(scene_name, resolution=(resolution, resolution), spp=1)
    desc = {"type": "partpm", "photon_count": photons, "map_count": maps}
    dr.eval(mi.render(scene, integrator=mi.load_dict({**desc, "photon_count": 10_000})))
    baseline = _rss_now()
    dr.detail.malloc_clear_statistics()
    integrator = mi.load_dict(desc)
    t0 = time.perf_counter()
    image = mi.render(scene, integrator=integrator)
    dr.eval(image)
    dr.sync_thread()
    return {"scene": scene_name, "photons": photons, "maps": maps, "variant": variant,
            "stored": int(integrator.stats["photons_stored"]),
            "seconds": time.perf_counter() - t0, "baseline_rss_bytes": baseline,
            "peak_rss_bytes": peak_rss_bytes(),
            "drjit_peak_bytes": int(dr.detail.malloc_watermark(dr.backend_v(mi.Float))),
            "stats": {k: v for k, v in integrator.stats.items()
                      if isinstance(v, (int, float))}}


def probe(scene_name: str, photons: int, maps: int = 8, timeout: float = 3600,
          variant: str = "llvm_ad_rgb") -> dict:
    """:func:`measure` in a fresh Python process."""
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "memory.json"
        done = subprocess.run([sys.executable, "-m", "mi_partpm.experiments.memprobe",
                               "--scene", scene_name, "--photons", str(photons), "--maps",
                               str(maps), "--variant", variant, "--out", str(out)],
                              capture_output=True, text=True,
                              timeout=timeout, env=os.environ.copy())
        if done.returncode != 0:
            raise RuntimeError(f"the memory probe of {photons:,} photons failed (exit "
                               f"{done.returncode}): {done.stderr.strip().splitlines()[-1:]}")
        return json.loads(out.read_text())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mi_partpm.experiments.memprobe",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="cornell_box")
    parser.add_argument("--photons", type=int, required=True)
    parser.add_argument("--maps", type=int, default=8)
    parser.add_argument("--variant", default="llvm_ad_rgb")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    Path(args.out).write_text(json.dumps(measure(args.scene, args.photons, args.maps,
                                                 variant=args.variant),
                                         indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
