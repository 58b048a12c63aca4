"""Where a result came from: the code that made it and the machine it ran on.

:func:`code_version` is a hash of the project's source files (the renderer, the plugins and
hwsim), so a cached run is reused only by the code that made it, with or without git;
:func:`machine` describes the machine. Every experiment records both beside its results.
"""
from __future__ import annotations

import hashlib
import os
import platform
import subprocess
from functools import lru_cache
from pathlib import Path

__all__ = ["code_version", "machine", "git_commit", "scene_digest"]

_ROOT = Path(__file__).resolve().parents[2]
#: The source folders whose files make a result (relative to the project's root).
SOURCES = ("mi_partpm", "integrators", "hwsim")
#: Files of :data:`SOURCES` that make no result: they only run the experiments and format
#: their results (``partpm figures``), so changing them reruns nothing.
NOT_RESULTS = ("mi_partpm/experiments/regenerate.py", "mi_partpm/experiments/readme.py",
               "mi_partpm/cli/figures.py")


@lru_cache(maxsize=1)
def code_version() -> str:
    """SHA-256 (first 16 hex digits) of every ``.py``, ``.xml`` and ``.toml`` file of
    :data:`SOURCES` but :data:`NOT_RESULTS`, in path order."""
    digest = hashlib.sha256()
    for folder in SOURCES:
        base = _ROOT / folder
        files = sorted(p for p in base.rglob("*") if p.suffix in (".py", ".xml", ".toml")
                       and "__pycache__" not in p.parts
                       and p.relative_to(_ROOT).as_posix() not in NOT_RESULTS)
        for path in files:
            digest.update(str(path.relative_to(_ROOT)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def git_commit() -> str:
    """The checkout's commit (with ``-dirty`` when files differ from it), or '' without git."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=_ROOT,
                                capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=_ROOT, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return ""
    if commit.returncode != 0:
        return ""
    return commit.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")


def _cpu_model() -> str:
    """The processor's model name (Linux: /proc/cpuinfo), or ''."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.lower().startswith(("model name", "hardware", "cpu model")):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return ""


def machine() -> dict:
    """The machine: processor (and its model), cores, memory, OS, Python, Mitsuba and Dr.Jit
    versions."""
    import drjit as dr
    import mitsuba as mi
    memory = None
    try:
        with open("/proc/meminfo") as f:
            memory = int(f.readline().split()[1]) * 1024
    except OSError:
        pass
    return {"processor": platform.processor() or platform.machine(), "model": _cpu_model(),
            "cores": os.cpu_count(), "memory_bytes": memory, "os": platform.platform(),
            "python": platform.python_version(), "mitsuba": mi.__version__,
            "drjit": dr.__version__, "threads": dr.thread_count()}


def simd_lanes() -> int:
    """Queries that run side by side in one packet of Dr.Jit's kernels on this machine: a
    CUDA warp's 32, or the LLVM backend's vector width
    (:func:`~mi_partpm.kdtree.radius.packet_lanes`)."""
    import mitsuba as mi
    if mi.variant() and mi.variant().startswith("cuda"):
        return 32
    from ..kdtree.radius import packet_lanes
    return packet_lanes()


def l1_data_bytes():
    """Bytes of one core's L1 data cache (Linux's sysfs), or None where it cannot be read."""
    base = Path("/sys/devices/system/cpu/cpu0/cache")
    try:
        for index in sorted(base.glob("index*")):
            if (index / "level").read_text().strip() == "1" and \
                    (index / "type").read_text().strip() in ("Data", "Unified"):
                text = (index / "size").read_text().strip().upper()
                scale = {"K": 1 << 10, "M": 1 << 20}.get(text[-1:], 1)
                return int(text.rstrip("KM")) * scale
    except (OSError, ValueError):
        pass
    return None


def scene_digest(scene: str, data_dir=None) -> str:
    """SHA-256 (16 hex digits) of a scene (built-in name or path): its file, the files it
    includes and the files its plugins name (:func:`~mi_partpm.scenes.scene_inputs`), and a
    built-in scene's data files, for caches that depend on the scene and not on the code (a
    changed include or mesh made a stale reference look current)."""
    from ..data import find_data_file
    from ..scenes import SCENE_DATA, scene_inputs, scene_path
    path = scene_path(scene).resolve()
    digest = hashlib.sha256(path.read_bytes())
    for file in scene_inputs(path):
        if file != path:                         # each other file by its name and bytes
            digest.update(str(file.relative_to(path.parent) if file.is_relative_to(path.parent)
                              else file).encode())
            digest.update(file.read_bytes())
    for name in SCENE_DATA.get(path.stem, {}).values():
        digest.update(find_data_file(name, data_dir).read_bytes())
    return digest.hexdigest()[:16]
