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
    except KeyboardInterrupt:
        print("partpm: interrupted", file=sys.stderr)
        return 130
    return command()


if __name__ == "__main__":
    sys.exit(main())
