"""The `mirage` entry point (and `python -m mirage_cli`): signal handlers first, then the
slow-to-import program. The console script points here, not at `cli.main`, so that a
Ctrl-C or SIGTERM while click, OpenCV, numba ... load is one line and exit 130 / 143."""

from . import signals


def run() -> None:
    signals.install()  # before any import below: from here on a signal is one line
    try:
        from .cli import main
    except (KeyboardInterrupt, ImportError) as e:  # a signal while OpenCV, numba ... load
        import sys

        intr = e
        while intr is not None and not isinstance(intr, KeyboardInterrupt):
            intr = intr.__cause__ or intr.__context__  # numba re-raises it as ImportError
        if intr is None:
            raise
        print(signals.message(intr), file=sys.stderr)
        sys.exit(signals.exit_code(intr))
    from .cli import end_within_grace, exit_without_teardown

    try:
        main()
    except SystemExit as e:
        end_within_grace(e.code)  # interrupted: Python's exit may not wait on threads
        exit_without_teardown(e.code)
        raise


if __name__ == "__main__":
    run()
