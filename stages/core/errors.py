"""User-facing errors shared by every stage.

A stage raises :class:`UserError` for bad input (a file it cannot read, a wrong artefact kind,
impossible geometry...). The CLI turns it into one line on stderr and a non-zero exit code, never a
traceback. Anything else escaping a stage is a bug and keeps its traceback.
"""


class UserError(Exception):
    """Bad input from the user: the message is shown as is, so it names the file and the problem."""

    exit_code = 2
