"""The project's error type: bad input is one line that says what to do, exit code 2."""

from __future__ import annotations

import difflib
import importlib.util
from collections.abc import Iterable


class CapVectorError(ValueError):
    """Raised for bad input (configs, files, checkpoints). The CLI prints it without a traceback."""


class UnknownNameError(CapVectorError, KeyError):
    """A name that is none of the known ones (task, scene variant, robot); a ``KeyError`` too, as
    the dictionary lookup it reports."""

    def __str__(self) -> str:  # KeyError's own would print the message in quotes
        return str(self.args[0]) if self.args else ""


def unknown_name(what: str, name: str, known: Iterable[str]) -> UnknownNameError:
    """``unknown task 'Liftt' (did you mean Lift?); known: Lift, Stack, PickPlaceCan``."""
    known = list(known)
    return UnknownNameError(
        f"unknown {what} {name!r}{did_you_mean(name, known)}; known: {', '.join(known)}"
    )


def did_you_mean(name: str, known: Iterable[str]) -> str:
    """`` (did you mean A or B?)`` for the known names close to ``name``; empty when none is."""
    close = difflib.get_close_matches(name, list(known), n=3)
    return f" (did you mean {' or '.join(close)}?)" if close else ""


def config_error(where: str, err: Exception) -> CapVectorError:
    """One line for an omegaconf error, whose message spans three (what, ``full_key``, type)."""
    message = str(getattr(err, "msg", None) or err).strip().splitlines()[0]
    key = getattr(err, "full_key", None)
    return CapVectorError(f"{where}: {message}" + (f" (at {key})" if key else ""))


class MissingExtraError(CapVectorError, ImportError):
    """An optional extra is not installed; an ``ImportError`` too, as the import it reports."""


def missing_extra(needed_for: str, extra: str, err: ImportError) -> MissingExtraError:
    """``the simulator needs the sim extra: pip install 'capvector[sim]' (No module named
    'mujoco')``: one line, as LeRobot names the extra of a missing environment package."""
    reason = (str(err).strip().splitlines() or [type(err).__name__])[0]
    return MissingExtraError(
        f"{needed_for} needs the {extra} extra: pip install 'capvector[{extra}]' ({reason})"
    )


def require_extra(needed_for: str, extra: str, *modules: str) -> None:
    """Stop before any work when ``extra``'s ``modules`` are not installed (looked up, not imported,
    so checking the simulator is there loads none of it)."""
    for module in modules:
        if importlib.util.find_spec(module) is None:
            missing = ModuleNotFoundError(f"No module named {module!r}", name=module)
            raise missing_extra(needed_for, extra, missing)
