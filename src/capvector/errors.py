"""The project's error type: bad input from the user, with a message that says what to do."""


class CapVectorError(ValueError):
    """Raised for bad input (configs, files, checkpoints). The CLI prints it without a traceback."""
