"""One exception base class: the CLI turns any MirageError into a one-line message and its
exit code (2: the user can fix the input; 1: the machine failed us, e.g. a full disk)."""


class MirageError(Exception):
    """A failure the user can fix (bad input, missing file, ...). Message says what and how."""

    exit_code = 2


class InputError(MirageError):
    """An input file or option is missing, unreadable or malformed."""


class OutputError(MirageError):
    """An output cannot be written."""


class NothingFound(MirageError):
    """The run went to the end, but no frame gave a pose (the landmark was never found).
    The outputs are written (each row says why); exit 3, so a script does not go on to
    report on an empty trajectory as if it had tracked."""

    exit_code = 3


class EnvironmentFailure(MirageError):
    """The machine, not the input: a full disk, an I/O error, a closed standard output.
    Exit 1, so scripts can tell it from a usage error."""

    exit_code = 1


def cv_message(e: Exception) -> str:
    """The informative last line of an OpenCV (or other) exception, for one-line errors."""
    s = str(e).strip()
    return s.splitlines()[-1] if s else type(e).__name__


class OptionError(InputError):
    """An option's value is wrong (`option` names it, e.g. '--end'); the CLI reports it as
    click's usage error for that option, other callers as an InputError."""

    def __init__(self, message: str, option: str):
        super().__init__(message)
        self.message, self.option = message, option
