"""Errors that the command line reports as one readable line."""


class CLIError(Exception):
    """User-facing error (bad option, unreadable input, failed run), printed without traceback."""

    def __init__(self, message: str, exit_code: int = 2):
        super().__init__(message)
        self.exit_code = exit_code
