"""The project's error type, and the argument parser every tool uses: bad input is one line that
says what to do, exit code 2."""

from __future__ import annotations

import argparse
from typing import NoReturn


class CapVectorError(ValueError):
    """Raised for bad input (configs, files, checkpoints). The CLI prints it without a traceback."""


class ToolParser(argparse.ArgumentParser):
    """argparse that reports a bad argument as one line, ``prog: error: ... (see prog --help)``,
    with exit code 2, instead of the usage block followed by the error."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")
