"""The ``partpm`` command's entry point, outside the package: ``import mi_partpm`` loads
Mitsuba and Dr.Jit (a third of a second and more), and a Ctrl-C in that time printed
Python's traceback from inside their imports, or stopped Dr.Jit half initialised. Here
Ctrl-C is held until they have loaded, and then ends the command as it does later:
``partpm: interrupted``, exit status 130. The command itself is :func:`mi_partpm.cli.main`.
"""
import signal
import sys


def main() -> int:
    held = hasattr(signal, "pthread_sigmask") and \
        signal.getsignal(signal.SIGINT) is signal.default_int_handler
    try:
        if held:
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            from mi_partpm.cli import main as command
        finally:
            if held:                  # a Ctrl-C held until now is raised here
                signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        return command()
    except KeyboardInterrupt:         # during the imports, or before the command's own
        print("partpm: interrupted", file=sys.stderr)     # handling began (an MPI job's start)
        _abort_the_job()
        return 130


#: Where mpiexec says how many ranks it started (MPICH's hydra, Open MPI), as
#: ``mi_partpm.backends.LAUNCHER_SIZE_VARIABLES`` reads them (not imported: this runs
#: before, or instead of, the package's imports).
LAUNCHER_SIZE_VARIABLES = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE")


def _abort_the_job():
    """A rank of an MPI job interrupted before the command started: the other ranks would
    wait for it in their first collective call for ever, so the whole job ends here."""
    import os
    if not any(os.environ.get(name, "").isdigit() and int(os.environ[name]) > 1
               for name in LAUNCHER_SIZE_VARIABLES):
        return
    try:
        from mpi4py import MPI
        MPI.COMM_WORLD.Abort(130)
    except ImportError:                 # no MPI: the job cannot be told, as before
        pass


if __name__ == "__main__":
    sys.exit(main())
