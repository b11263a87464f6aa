"""`python -m mirage_cli`: signal handlers first, then the (slow to import) program."""

from . import signals

signals.install()
try:
    from .cli import main
except KeyboardInterrupt as e:  # Ctrl-C or SIGTERM while importing OpenCV, numba, ...
    import sys

    print(signals.message(e), file=sys.stderr)
    sys.exit(signals.exit_code(e))

main()
