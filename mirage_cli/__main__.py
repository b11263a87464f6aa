"""The `mirage` entry point (and `python -m mirage_cli`): signal handlers first, then the
slow-to-import program. The console script points here, not at `cli.main`, so that a
Ctrl-C or SIGTERM while click, OpenCV, numba ... load is one line and exit 130 / 143."""

from . import signals


def run() -> None:
    signals.install()  # before any import below: from here on a signal is one line
    try:
        from .cli import main
    except KeyboardInterrupt as e:  # Ctrl-C or SIGTERM while importing OpenCV, numba, ...
        import sys

        print(signals.message(e), file=sys.stderr)
        sys.exit(signals.exit_code(e))
    main()


if __name__ == "__main__":
    run()
