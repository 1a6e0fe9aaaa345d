"""The one error type the command line turns into a single clear line and exit code."""


class SpikegenError(Exception):
    """A problem with the user's input: the message names what is wrong and where."""

    exit_code = 2


class InputError(SpikegenError):
    """A bad input file or argument value."""


class OutputError(SpikegenError):
    """The output cannot be written (unwritable, full disk, would overwrite)."""

    exit_code = 3
