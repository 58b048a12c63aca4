"""Where the n maps run: this process, or the ranks of an MPI job. One object, chosen once.

:class:`LocalBackend` owns every map. With :class:`MPIBackend`, rank j of P owns maps j, j+P,
j+2P, ... It traces exactly those maps' photons from their own random streams (the stream of
map i depends on (seed, i) only, never on P), builds their trees and evaluates them at the
eye-ray hits, which every rank generates identically. No rank holds another's photons.

The integrators talk to a backend only through :class:`Backend`'s methods, so the phases have
no MPI branches. The gather is one ``MPI_Allreduce`` per pass of every eye path's flux and
photon count (:meth:`Backend.allreduce`): every rank then updates the same progressive
statistics, and rank 0, which alone adds emission and direct light, holds the image.

mpi4py is imported only when the MPI backend is used; ``pip install mpi4py mpich`` gives a
working ``mpiexec`` from PyPI, and a cluster's own MPI works the same.
"""
from __future__ import annotations

import logging
import os
import shutil
import sys
import time
import traceback
from contextlib import contextmanager, nullcontext
from pathlib import Path

import drjit as dr
import numpy as np

__all__ = ["launcher_ranks", "launcher_rank", "run_as_one_job", "abort_job", "report_error", "interrupted",
           "Backend", "LocalBackend", "MPIBackend", "make_backend", "BACKENDS", "comm_world",
           "owned_maps", "check_ranks", "allreduce_arrays", "abort_on_error",
           "share_cores", "find_mpiexec", "MPIUnavailable", "job_stats"]

log = logging.getLogger("mi_partpm")

#: The values of the ``backend`` prop.
BACKENDS = ("local", "mpi")


class MPIUnavailable(RuntimeError):
    """backend='mpi' was asked for, but mpi4py (or an MPI library) is not installed."""


def comm_world():
    """``MPI.COMM_WORLD``, or a clear error when MPI is missing."""
    try:
        from mpi4py import MPI
    except ImportError as e:
        raise MPIUnavailable(
            f"backend 'mpi' needs mpi4py and an MPI library ({e}); install them with "
            f"'pip install mpi4py mpich' (or use your cluster's MPI) and start the job with "
            f"mpiexec -n P") from None
    return MPI.COMM_WORLD


def share_cores(comm) -> int:
    """Give each rank its share of this machine's cores for Dr.Jit's thread pool, and of its
    free memory for the memory guard (:func:`~mi_partpm.memory.share_memory`).

    Ranks on the same node would otherwise each start one thread per core. Never fewer than
    2: with a pool of one thread (Dr.Jit 1.5), writing a ``mi.Bitmap`` deadlocks. Returns the
    thread count set: ``PARTPM_THREADS`` per rank where it is set (Dr.Jit 1.5 reads no
    variable of its own for this: a ``DRJIT_NUM_THREADS`` was left to it, which ignored it).
    """
    from mpi4py import MPI

    from .memory import share_memory
    node = comm.Split_type(MPI.COMM_TYPE_SHARED)
    here = node.size
    node.Free()
    share_memory(here)          # and its share of the free memory
    given = os.environ.get("PARTPM_THREADS")
    if given:
        try:
            threads = int(given)
        except ValueError:
            threads = 0
        if threads < 1:
            raise ValueError(f"PARTPM_THREADS (Dr.Jit threads per MPI rank) must be an "
                             f"integer >= 1, got {given!r}")
        threads = max(2, threads)
    else:
        threads = max(2, (os.cpu_count() or 1) // here)
    dr.set_thread_count(threads)
    return threads


#: Words of the one error that every rank of a job raises alike (:func:`check_ranks`).
EVERY_RANK_FAILS = "every rank owns at least one map"


def check_ranks(ranks: int, map_count: int):
    """P must not exceed n: a rank without a map would have nothing to do."""
    if ranks > map_count:
        raise ValueError(f"the MPI job has {ranks} ranks but map_count is {map_count}: "
                         f"{EVERY_RANK_FAILS}, so use at most {map_count} "
                         f"rank{'s' if map_count != 1 else ''} or raise "
                         f"map_count to >= {ranks}")


def owned_maps(rank: int, ranks: int, map_count: int) -> np.ndarray:
    """The maps of rank ``rank`` of ``ranks``: rank, rank + ranks, ... (round robin)."""
    return np.arange(rank, map_count, ranks, dtype=np.int64)


def abort_job(comm, message, code: int = 1, alone: bool = False):
    """End the whole MPI job from this rank: print ``message`` (None: the rank printed its
    own; ``alone``: an error no other rank can find, said at once), give mpiexec a moment
    to forward it, abort, and exit (where the abort returns before it ends this process)."""
    try:
        if message:
            report_error(comm, message, alone)
    except BaseException:      # noqa: BLE001  (nothing may keep the job from ending)
        pass
    if comm.size == 1:         # no rank to stop: MPI_Abort of a lone rank ran the C++ exit
        sys.stdout.flush()     # handlers under Dr.Jit's live threads (terminate, exit 6)
        sys.stderr.flush()
        os._exit(code)
    # A rank that left the message to rank 0 waits longer, so that rank 0, which fails alike
    # at about the same time, says it before the job ends.
    time.sleep(SILENT_RANK_WAIT if _SILENCED else 1.0)
    comm.Abort(code)
    os._exit(code)


#: Seconds a rank that left its message to rank 0 waits before it ends the job.
SILENT_RANK_WAIT = 5.0
#: Seconds a rank other than 0 waits before it says its error: where rank 0 fails alike (the
#: same options, the same scene on every rank), rank 0 says it and ends the job first, so
#: the job says it once; an error of this rank alone is said after that wait.
ROOT_FIRST_WAIT = 3.0
#: Whether this rank left an error's message to rank 0 (:func:`report_error`).
_SILENCED = False


def report_error(comm, message: str, alone: bool = False):
    """Print ``partpm: error[ on MPI rank j of P]: message`` on standard error, as one write
    (the lines of ranks that fail at once ran together when the newline was written apart).
    Ranks other than 0 first wait :data:`ROOT_FIRST_WAIT` seconds, in which rank 0, failing
    alike, says it and ends the job; for the error that every rank raises alike
    (:func:`check_ranks`: found by its words, as Mitsuba passes an integrator's error on as a
    new exception with the same text) they say nothing, so the job says it once. An error
    of this rank ``alone`` is said at once."""
    global _SILENCED
    where = "" if comm is None else f" on MPI rank {comm.rank} of {comm.size}"
    if comm is not None and comm.rank != 0:
        if EVERY_RANK_FAILS in message:
            _SILENCED = True
            return
        if not alone:
            time.sleep(ROOT_FIRST_WAIT)
    line = f"partpm: error{where}: {message}\n"
    try:
        sys.stderr.flush()
        data, fd = line.encode("utf-8", "replace"), sys.stderr.fileno()
        while data:                            # os.write may write part of it
            data = data[os.write(fd, data):]
    except (AttributeError, OSError, ValueError):  # no descriptor (a notebook, a test's capture)
        if sys.stderr is not None:
            sys.stderr.write(line)
            sys.stderr.flush()


def interrupted(e: BaseException) -> bool:
    """Whether ``e`` is Ctrl-C: a KeyboardInterrupt, or an error that Mitsuba or Dr.Jit
    raised because of one (``mi.render`` wraps what interrupts it in a RuntimeError)."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def _message(e: BaseException) -> str:
    if interrupted(e):
        return "interrupted (Ctrl-C): the job stops at once, with no image"
    if isinstance(e, SystemExit):
        return f"the rank exited (SystemExit {e.code!r}) during the render"
    return str(e) if type(e).__name__ == "UsageError" else \
        traceback.format_exception_only(type(e), e)[-1].strip()


def _exit_code(e: BaseException, default: int) -> int:
    if interrupted(e):
        return 130
    if isinstance(e, SystemExit) and isinstance(e.code, int) and e.code:
        return e.code
    return default


@contextmanager
def abort_on_error(comm, describe=None):
    """Turn an exception on one rank into an abort of the whole job with that rank's message.

    Without it the other ranks would wait in the reduction forever: so also for
    ``SystemExit`` (``sys.exit`` in a callback) and ``KeyboardInterrupt``. ``describe``, when
    given, turns a bad-input error (``ValueError``, ``RuntimeError``, ``MemoryError``) into
    the message to print, and the job exits with 2, as the command line does for bad input
    (it names its options where the integrator names its props). A job of one rank raises
    the exception as a local render would (a notebook's kernel is not ended).
    """
    try:
        yield
    except (Exception, SystemExit, KeyboardInterrupt) as e:   # noqa: BLE001
        if comm.size == 1:
            raise          # no other rank waits for this one: the caller hears of it as usual
        if describe is not None and isinstance(e, (ValueError, RuntimeError, MemoryError)) \
                and not interrupted(e):
            try:
                message = describe(e)
            except Exception:   # noqa: BLE001  (nothing may keep the job from ending)
                message = _message(e)
            abort_job(comm, message, 2)
        abort_job(comm, _message(e), _exit_code(e, 1))


#: Variables that MPI launchers set in every rank's environment, with the job's rank count
#: (MPICH's and Intel MPI's Hydra, Open MPI's mpirun), and with the rank's own number.
LAUNCHER_SIZE_VARIABLES = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE")
LAUNCHER_RANK_VARIABLES = ("PMI_RANK", "OMPI_COMM_WORLD_RANK")


def launcher_rank() -> int:
    """This process's rank in the MPI job mpiexec started it in (0 when it was not), from
    the launcher's environment."""
    for name in LAUNCHER_RANK_VARIABLES:
        value = os.environ.get(name, "")
        if value.isdigit():
            return int(value)
    return 0


def launcher_ranks() -> int:
    """The ranks of the MPI job this process was started in by mpiexec, from the launcher's
    environment (1 when it was not: nothing is imported or initialised to find out)."""
    for name in LAUNCHER_SIZE_VARIABLES:
        value = os.environ.get(name, "")
        if value.isdigit():
            return int(value)
    return 1


def run_as_one_job(comm, argv, run) -> int:
    """Run a command (``run()``, which returns its exit status) on every rank of ``comm`` as
    one job: the ranks must have been given the same arguments ``argv``, and a rank that
    fails, before or during the render (an error, or a status other than 0), ends the whole
    job (a rank that just exited would leave the others waiting in their next collective
    call)."""
    try:
        first = comm.bcast(list(argv), root=0)
        if list(argv) != first:     # found by this rank alone: said at once
            abort_job(comm, f"the ranks of the MPI job were started with different arguments "
                            f"(rank 0: {' '.join(first)}; rank {comm.rank}: {' '.join(argv)}): "
                            f"start every rank with the same command", 2, alone=True)
        code = run()
    except SystemExit as e:      # argparse has printed its message
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    except (Exception, KeyboardInterrupt) as e:   # noqa: BLE001  (any failure ends the job)
        abort_job(comm, _message(e), _exit_code(e, 2))
    if code:
        abort_job(comm, None, code)         # the rank has said why
    return 0


def find_mpiexec() -> str:
    """The venv's ``mpiexec`` (from the ``mpich`` wheel), else the first on PATH."""
    beside = Path(sys.executable).parent / "mpiexec"
    if beside.is_file():
        return str(beside)
    found = shutil.which("mpiexec")
    if not found:
        raise FileNotFoundError("no mpiexec found beside Python or on PATH: install MPI with "
                                "'pip install mpi4py mpich' (or load your cluster's MPI)")
    return found


class Backend:
    """Where the maps of a render run. Subclasses: :class:`LocalBackend`, :class:`MPIBackend`.

    Attributes
    ----------
    name : str
        The ``backend`` prop's value.
    emission_weight : float
        Weight of the terms that do not come from the photon maps (emission, direct light):
        1 on exactly one process of a render (the root), 0 elsewhere.
    """

    name = "local"
    emission_weight = 1.0

    def owned_maps(self, map_count: int) -> np.ndarray:
        """The maps this process traces, builds and queries."""
        return np.arange(map_count)

    def running(self):
        """Context for a render: what to do when it fails."""
        return nullcontext()

    def start(self):
        """Called by every process at the start of each render, inside :meth:`running`:
        what needs all of them at once (not when the integrator is made: a script may make
        one on some ranks only)."""

    def allreduce(self, values, stats: dict):
        """Sum per-lane arrays (``mi.Spectrum`` / ``mi.Float``) over the processes, every
        process receiving the sum: a progressive pass's flux and photon counts."""
        return values

    def agree(self, stop: bool) -> bool:
        """Whether every process stops after this pass: any process's ``stop`` (its time
        limit, or a Ctrl-C it received)."""
        return stop

    def root_says(self, value: bool) -> bool:
        """The root process's ``value`` on every process (whether a time limit is reached:
        by the root's clock, which leaves out the time its ``on_pass`` took, as the other
        processes waited for it)."""
        return value

    def collect(self, stats: dict) -> dict:
        """Every process's ``stats`` on the root (for reporting), and the whole job's
        figures in the root's own (:func:`job_stats`)."""
        return stats

    def total(self, value: int) -> int:
        """``value`` summed over the processes, every process receiving the sum (the
        photons stored in all maps, where a warning says there were none)."""
        return value

    def check_same(self, settings: dict):
        """Refuse a render whose processes disagree on ``settings`` (the film, the samples,
        the seed, the scene's size): their partial images would not add up to one image."""

    @property
    def reports(self) -> bool:
        """Whether this process says what is true of the whole render (the root): the
        warnings that every process would give alike."""
        return self.is_root

    @property
    def is_root(self) -> bool:
        """Whether this process returns (and writes) the whole image."""
        return True


class LocalBackend(Backend):
    """Every map in this process; Dr.Jit spreads each kernel over the cores (or the GPU)."""


class MPIBackend(Backend):
    """Rank j of P owns maps j, j+P, ...; one ``MPI_Allreduce`` per pass is the gather."""

    name = "mpi"

    def __init__(self, map_count: int):
        self.comm = comm_world()
        check_ranks(self.comm.size, map_count)
        self.emission_weight = 1.0 if self.comm.rank == 0 else 0.0
        self._shared = False

    def start(self):
        # The node's ranks are counted by a split that every rank makes together: here, not
        # in __init__ (an integrator made on one rank only waited there for the others).
        if not self._shared:
            share_cores(self.comm)
            self._shared = True

    @property
    def is_root(self) -> bool:
        return self.comm.rank == 0

    def owned_maps(self, map_count: int) -> np.ndarray:
        return owned_maps(self.comm.rank, self.comm.size, map_count)

    #: Set by the command line: how a bad-input error of the render reads to its user
    #: (:func:`abort_on_error`); None: the exception's type and text.
    describe = None

    def running(self):
        return abort_on_error(self.comm, self.describe)

    def allreduce(self, values, stats: dict):
        t0 = time.perf_counter()
        out, nbytes = allreduce_arrays(self.comm, values)
        stats["time_reduce"] = stats.get("time_reduce", 0.0) + time.perf_counter() - t0
        stats["reduce_bytes"] = stats.get("reduce_bytes", 0) + nbytes
        return out

    def agree(self, stop: bool) -> bool:
        from mpi4py import MPI
        return bool(self.comm.allreduce(bool(stop), op=MPI.LOR))

    def root_says(self, value: bool) -> bool:
        return bool(self.comm.bcast(bool(value), root=0))

    def collect(self, stats: dict) -> dict:
        stats.pop("ranks", None)          # a list of an earlier render's ranks
        stats["rank"] = self.comm.rank
        ranks = self.comm.gather(dict(stats), root=0)   # reporting only
        if self.is_root:
            stats.update(job_stats(ranks), ranks=ranks)
        return stats

    def total(self, value: int) -> int:
        return int(self.comm.allreduce(int(value)))

    def check_same(self, settings: dict):
        every = self.comm.allgather(settings)
        differ = [key for key in settings if any(s.get(key) != every[0].get(key)
                                                 for s in every)]
        if differ:
            said = "; ".join(f"{key}: " + ", ".join(f"rank {j} {s.get(key)!r}"
                                                     for j, s in enumerate(every))
                             for key in differ)
            raise ValueError(f"the ranks of the MPI job render different things ({said}): "
                             f"every rank must render the same scene file with the same "
                             f"film, samples and seed, or their images do not add up")


def job_stats(ranks: list) -> dict:
    """The whole job's figures from every rank's stats: the photons, segments, tree bytes
    and CPU seconds summed over the ranks, the wall times, waves and peak memory the
    largest rank's (the slowest rank's times), the maps all of them, and ``stopped_by`` the
    first reason of a rank that stopped on its own."""
    job = {}
    for key in ranks[0]:
        values = [r.get(key) for r in ranks]
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            continue
        if key.endswith(("photons_stored", "photons_traced")) or key in ("segments",
                                                                         "map_bytes") \
                or key.startswith("cpu_"):
            job[key] = sum(values)
        elif key.startswith("time_") or key in ("waves", "peak_memory_bytes"):
            job[key] = max(values)
    job["maps_owned"] = sorted(m for r in ranks for m in r.get("maps_owned", []))
    # Why the job ended early: the reason of a rank that stopped on its own (a Ctrl-C to it,
    # its time limit), not of one that stopped because another did.
    reasons = [r["stopped_by"] for r in ranks if r.get("stopped_by")]
    own = [why for why in reasons if why != "another_process"]
    if reasons:
        job["stopped_by"] = (own or reasons)[0]
    return job


def allreduce_arrays(comm, values):
    """Sum Dr.Jit arrays over the ranks in one ``MPI_Allreduce`` (float32, packed); returns
    the sums (same types) and the bytes each rank sent."""
    from mpi4py import MPI
    flat = [dr.ravel(v).numpy().astype(np.float32) for v in values]
    send = np.concatenate(flat)
    recv = np.empty_like(send)
    comm.Allreduce(send, recv, op=MPI.SUM)
    out, offset = [], 0
    for v, f in zip(values, flat):
        out.append(dr.unravel(type(v), type(dr.ravel(v))(recv[offset:offset + f.size])))
        offset += f.size
    return out, int(send.nbytes)


def make_backend(name: str, map_count: int) -> Backend:
    """The backend called ``name`` (one of :data:`BACKENDS`) for ``map_count`` maps."""
    return MPIBackend(map_count) if name == "mpi" else LocalBackend()
