"""One registry for every kind of plugin: backbone families and presets, StarVLA action heads,
spatial-alignment teachers and auxiliary objectives.

A plugin is found by the name it was registered under (``@HEADS.register("oft")``), or by an import
path ``module:Name``, which imports ``module`` first: ``Name`` is then a name that module registered
(``my_pkg.my_vla:my-preset``) or one of its attributes (``my_pkg.heads:MyHead``). A registry may
name built-in modules to import on first use, so ``import capvector`` stays light, and an
entry-point group through which installed packages add their modules. An unknown name is one line
that lists the close names and the known ones.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from types import ModuleType
from typing import Any, Generic, TypeVar

from capvector.errors import CapVectorError, UnknownNameError, did_you_mean

T = TypeVar("T")
S = TypeVar("S")


class Registry(Generic[T]):
    """Named plugins of one kind.

    Args:
        kind: what the plugins are, for messages ("action head", "backbone preset").
        modules: modules that register the built-in plugins, imported on first use.
        group: an entry-point group; its entry points name modules that register plugins, imported
            only when a name is not found otherwise (a broken package cannot break the built-ins).
        base: the class plugins subclass; an attribute found by ``module:Name`` must be one.
        error: the error type raised for names that resolve to nothing.
        plugin: what a module named in ``module:Name`` defines, for messages (default ``kind``).
    """

    def __init__(
        self,
        kind: str,
        *,
        modules: Sequence[str] = (),
        group: str | None = None,
        base: type | None = None,
        error: type[CapVectorError] = UnknownNameError,
        plugin: str | None = None,
    ) -> None:
        self.kind = kind
        self.modules = tuple(modules)
        self.group = group
        self.base = base
        self.error = error
        self.plugin = plugin or kind
        self._entries: dict[str, T] = {}
        self._loaded: set[str] = set()

    def register(self, name: str) -> Callable[[S], S]:
        """Decorator: registers the decorated class or function as ``name``."""

        def decorate(obj: S) -> S:
            self.add(name, obj)  # type: ignore[arg-type]
            return obj

        return decorate

    def add(self, name: str, obj: T) -> None:
        if self._entries.get(name, obj) is not obj:
            raise ValueError(f"{self.kind} {name!r} is registered twice")
        self._entries[name] = obj

    def get(self, name: str) -> T:
        """The plugin registered as ``name``, or named by ``module:Name``."""
        self._import_builtins()
        module, sep, attr = name.rpartition(":")
        if sep:
            found = self._from_module(self.import_module(module), attr)
            if found is not None:
                return found
        elif name in self._entries:
            return self._entries[name]
        self._load_entry_points()
        if attr in self._entries:
            return self._entries[attr]
        where = f" in module {module!r}" if sep else ""
        raise self.error(
            f"unknown {self.kind} {attr!r}{where}{did_you_mean(attr, self._entries)}; known: "
            f"{', '.join(map(repr, sorted(self._entries)))}.{self._hint()}"
        )

    def entries(self) -> dict[str, T]:
        """Every registered plugin by name: the built-in ones and those of the entry points."""
        self._import_builtins()
        self._load_entry_points()
        return dict(sorted(self._entries.items()))

    def names(self) -> list[str]:
        return list(self.entries())

    def import_module(self, module: str) -> ModuleType:
        """Import ``module`` (it registers its plugins), with one clear error when it fails."""
        try:
            imported = importlib.import_module(module)
        except ImportError as err:
            raise self.error(
                f"cannot import {self.plugin} module {module!r} ({err}); install the package that "
                "defines it or put it on PYTHONPATH"
            ) from err
        self._loaded.add(module)
        return imported

    @contextmanager
    def scoped(self) -> Iterator[None]:
        """Registrations made inside the block are undone after it (tests, examples)."""
        self._import_builtins()
        entries, loaded = dict(self._entries), set(self._loaded)
        try:
            yield
        finally:
            self._entries, self._loaded = entries, loaded

    def _from_module(self, module: ModuleType, attr: str) -> T | None:
        if attr in self._entries:
            return self._entries[attr]
        found = getattr(module, attr, None)
        if found is None:
            return None
        if self.base is not None and not (isinstance(found, type) and issubclass(found, self.base)):
            raise self.error(
                f"{module.__name__}:{attr} is not a {self.kind}: not a subclass of "
                f"{self.base.__name__}"
            )
        return found

    def _import_builtins(self) -> None:
        for module in self.modules:
            if module not in self._loaded:
                self.import_module(module)

    def _load_entry_points(self) -> None:
        if self.group is None or "entry points" in self._loaded:
            return
        self._loaded.add("entry points")
        from importlib.metadata import entry_points

        for point in entry_points(group=self.group):
            try:
                point.load()
            except Exception as err:
                raise self.error(
                    f"{self.plugin} entry point {point.name!r} = {point.value!r} (group "
                    f"{self.group!r}) failed to import: {err}"
                ) from err

    def _hint(self) -> str:
        placeholder = "YourClass" if self.base else self.kind.rsplit(" ", 1)[-1]
        installed = (
            f", or install a package with a {self.group!r} entry point" if self.group else ""
        )
        return f" One of your own: name it `your.module:{placeholder}`{installed}."


def import_object(path: str, what: str) -> Any:
    """The object at ``module:Name`` or ``module.Name`` (``what`` it is, for messages): for code
    that takes any class, registered or not (``ExternalTeacher``'s feature model)."""
    module, sep, attr = path.rpartition(":") if ":" in path else path.rpartition(".")
    if not sep or not module:
        raise CapVectorError(f"{what} {path!r} is not an import path `module:Name`")
    try:
        imported = importlib.import_module(module)
    except ImportError as err:
        raise CapVectorError(f"{what} {path!r}: cannot import {module!r} ({err})") from err
    if not hasattr(imported, attr):
        public = [n for n in vars(imported) if not n.startswith("_")]
        raise CapVectorError(
            f"{what} {path!r}: module {module!r} has no {attr!r}{did_you_mean(attr, public)}"
        )
    return getattr(imported, attr)


__all__ = ["Registry", "import_object"]
