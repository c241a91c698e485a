"""The tools' command lines, built from typed functions by jsonargparse: a parameter is an option
(``--name-with-dashes``, required without a default; a positional-only one is a positional), its
annotation its type, its ``Args:`` docstring entry its help; a dataclass parameter (settings a
library function takes too) is one option per field, helped by the dataclass's ``Attributes:``.
``--config FILE`` reads options from YAML (keys the parameter and field names) and
``--print_config`` prints them, unless the function has a ``config`` parameter of its own (the
recipe's).

The spellings stay argparse's, which recipes, docs and scripts use: a ``bool`` is ``--flag`` /
``--no-flag``; a list is ``--opt A B ...``; a list of ``NamedTuple`` records is an option given
once per record, with its fields as values (report's ``--arm LABEL GLOB START``) or one value
that the record's ``parse`` reads (merge's ``--vector DIR:λ``).

A bad argument raises ``CapVectorError`` (one line, naming ``--help``), which ``capvector.cli``
prints as all bad input: exit code 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import re
import sys
import typing
from collections.abc import Callable, Collection, Sequence
from dataclasses import MISSING
from typing import Any

from capvector.errors import CapVectorError


def run_tool(
    function: Callable[..., object], argv: Sequence[str] | None, name: str, **fixed: Any
) -> int:
    """``capvector NAME ARGV``: ``function`` called with the options of ``argv`` (default
    ``sys.argv[1:]``) and with ``fixed``, the arguments that are not options (e.g. the command
    line, for a model card). Returns the exit code, 0."""
    tool = Tool(function, name, skip=fixed)
    tool.call(tool.parse(argv), **fixed)
    return 0


class Tool:
    """The parser of ``capvector NAME``: one option per parameter of ``function`` (per field of a
    dataclass parameter) but ``skip`` and ``**kwargs``; ``parser.add_argument`` adds more
    (import-original's, per family)."""

    def __init__(self, function: Callable[..., object], name: str, skip: Collection[str] = ()):
        from jsonargparse import ActionConfigFile, ArgumentParser

        description, helps = _documented(function)
        self.function, self.hints = function, typing.get_type_hints(function)
        self.records: dict[str, Any] = {}  # parameter: its NamedTuple, built after parsing
        self.groups: dict[str, Any] = {}  # parameter: its dataclass, built after parsing
        self.parser = ArgumentParser(
            prog=f"capvector {name}", description=description, exit_on_error=False
        )
        parameters = inspect.signature(function).parameters
        self.reads_config = "config" not in parameters
        if self.reads_config:
            self.parser.add_argument("--config", action=ActionConfigFile, help="options from YAML")
        for param in parameters.values():
            if param.name in skip or param.kind is param.VAR_KEYWORD:
                continue
            if dataclasses.is_dataclass(self.hints[param.name]):
                self._add_fields(param.name, self.hints[param.name])
            else:
                self._add(param, self.hints[param.name], helps.get(param.name))

    def _add_fields(self, name: str, settings: type) -> None:
        """A dataclass parameter: one option per field, documented where the dataclass is."""
        self.groups[name] = settings
        _, helps = _documented(settings)
        hints = typing.get_type_hints(settings)
        self.hints.update(hints)
        for field in dataclasses.fields(settings):
            default = inspect.Parameter.empty if field.default is MISSING else field.default
            param = inspect.Parameter(field.name, inspect.Parameter.KEYWORD_ONLY, default=default)
            self._add(param, hints[field.name], helps.get(field.name))

    def _add(self, param: inspect.Parameter, hint: Any, doc: str | None) -> None:
        kwargs: dict[str, Any] = {"help": doc, "type": hint}
        if param.default is not param.empty:  # argparse appends to a list, not to a tuple
            default = param.default
            kwargs["default"] = list(default) if type(default) is tuple else default
        item = _list_item(hint)
        if hint is bool:
            kwargs.update(type=None, action=argparse.BooleanOptionalAction)
        elif hasattr(item, "_fields"):  # kept as given here, made records by `parse`
            self.records[param.name] = item
            fields = () if hasattr(item, "parse") else tuple(f.upper() for f in item._fields)
            kwargs.update(type=None, action="append", nargs=len(fields) or None)
            kwargs["metavar"] = fields or None
        elif item is not None:
            kwargs.update(type=item, nargs="+" if kwargs.get("default") is None else "*")
        if param.kind is not param.POSITIONAL_ONLY:
            required = param.default is param.empty
            self.parser.add_argument(_flag(param.name), required=required, **kwargs)
            return
        if param.default is not param.empty:  # absent: the default, not over a --config's value
            kwargs.update(nargs=kwargs.get("nargs", "?"), default=argparse.SUPPRESS)
        self.parser.add_argument(param.name, **kwargs)

    def parse(self, argv: Sequence[str] | None) -> dict[str, Any]:
        """The options of ``argv`` (default ``sys.argv[1:]``), by parameter name."""
        try:
            parsed = self.parser.parse_args(sys.argv[1:] if argv is None else list(argv))
            # A class-typed option (report's --logger LoggerClass --logger.save_dir D) is built.
            values = self.parser.instantiate(parsed).as_dict()
            for name, record in self.records.items():
                if values[name] is not None:
                    values[name] = [_record(record, name, value) for value in values[name]]
            for name, settings in self.groups.items():
                fields = [field.name for field in dataclasses.fields(settings)]
                values[name] = settings(**{field: values.pop(field) for field in fields})
        except argparse.ArgumentError as err:
            message = " ".join(line.strip() for line in str(err).strip().splitlines())
            # jsonargparse's own, over several lines: 'Parser key "x": ... Given value: y'
            key = re.match(r'Parser key "(\w+)": .*(?:Got|Given) value: (.*)$', message)
            if key and key[1] in self.hints:
                hint = self.hints[key[1]]
                kind = hint.__name__ if isinstance(hint, type) else str(hint).replace("typing.", "")
                message = f"argument {_flag(key[1])}: expected {kind}, got {key[2]}"
            raise CapVectorError(f"{message} (see {self.parser.prog} --help)") from err
        if self.reads_config:
            values.pop("config")  # the files read, not an option
        return values

    def call(self, values: dict[str, Any], **fixed: Any) -> object:
        """``function`` with ``values`` and ``fixed``, its positional-only parameters by position."""
        values, parameters = dict(values), inspect.signature(self.function).parameters.values()
        given = [p.name for p in parameters if p.kind is p.POSITIONAL_ONLY and p.name in values]
        return self.function(*[values.pop(name) for name in given], **values, **fixed)


def _documented(function: Callable[..., object] | type) -> tuple[str | None, dict[str, str]]:
    """The description of a function or dataclass, and the help of each parameter or field from
    its ``Args:`` or ``Attributes:`` docstring entry."""
    import docstring_parser

    doc = docstring_parser.parse(inspect.getdoc(function) or "")
    helps = {  # an entry may document several parameters: "aux, sft: ..."
        name.strip(): " ".join(p.description.split())
        for p in doc.params
        for name in p.arg_name.split(",")
        if p.description
    }
    return doc.description, helps


def _list_item(hint: Any) -> Any:
    """``X`` for ``list[X]``, ``Sequence[X]`` or ``tuple[X, ...]``, or one of them ``| None``."""
    if type(None) in typing.get_args(hint):
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (list, Sequence) or (origin is tuple and args[1:] == (Ellipsis,)):
        return args[0]
    return None


def _record(record: Any, name: str, value: Any) -> Any:
    """One record from its values, as given on the command line or in a config file."""
    try:
        if hasattr(record, "parse"):
            return record.parse(value)
        if isinstance(value, str) or len(value) != len(record._fields):
            raise ValueError(f"expected {' '.join(record._fields).upper()}, got {value!r}")
        return record(*value)
    except ValueError as err:  # CapVectorError is one
        raise argparse.ArgumentError(None, f"argument {_flag(name)}: {err}") from err


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")
