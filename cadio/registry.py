"""Registries: named entries of one kind that their own modules add on import.

A completion method, a relation method or a relation input is one module that registers its
entry (name, role, one-line summary, the hooks its stage calls), as timm's ``register_model``
registers a model: the stages, the reports, the CLI's choices and the model cards read the
registry, never a list of names of their own. A registry imports every module of its package
the first time it is read, so a new module there is found without an edit anywhere else; a
test registers a toy entry for a while with ``registered``, and a stage that works in worker
processes hands them its ``foreign`` entries (those from outside the package).

Entries are listed by ``order``, then name: tables show the method under test first and its
baselines after, whatever the modules' file names.
"""

from __future__ import annotations

import hashlib
import importlib
import pkgutil
from collections.abc import Iterable, Iterator
from contextlib import ExitStack, contextmanager
from enum import StrEnum
from pathlib import Path
from typing import Generic, Protocol, TypeVar


class Role(StrEnum):
    """What an entry is to the product: the method it ships, or a baseline it is judged by."""

    OURS = "ours"
    BASELINE = "baseline"


class Named(Protocol):
    @property
    def name(self) -> str: ...

    @property
    def order(self) -> int: ...


T = TypeVar("T", bound=Named)


class UnknownEntry(KeyError):
    """A name no entry of the registry has; the message lists the names it has."""

    def __init__(self, kind: str, name: str, known: tuple[str, ...]) -> None:
        self.kind, self.name, self.known = kind, name, known
        super().__init__(f"unknown {kind} {name!r}; known: {', '.join(known) or 'none'}")

    def __str__(self) -> str:
        return str(self.args[0])


class Registry(Generic[T]):
    """The entries of one kind (``kind`` names it in messages), found in ``package``."""

    def __init__(self, kind: str, package: str) -> None:
        self.kind, self.package = kind, package
        self._entries: dict[str, T] = {}
        self._loaded = False

    def register(self, entry: T) -> T:
        """Add an entry (its module calls this on import); returns it, so a module may keep it.

        Raises:
            ValueError: another entry already has the name.
        """
        held = self._entries.get(entry.name)
        if held is not None and held != entry:
            raise ValueError(f"{self.kind} {entry.name!r} is registered twice")
        self._entries[entry.name] = entry
        return entry

    @contextmanager
    def registered(self, entry: T) -> Iterator[T]:
        """The entry registered for the ``with`` block, then removed (for tests)."""
        self._load()
        self.register(entry)
        try:
            yield entry
        finally:
            self._entries.pop(entry.name, None)

    def foreign(self) -> tuple[T, ...]:
        """The entries registered from outside the package (a test's, an embedding program's):
        a worker process finds the package's own on import and is handed these
        (``including``), so their hooks must be picklable (module-level functions)."""
        self._load()
        return tuple(e for e in self._entries.values()
                     if not str(getattr(e, "module", "")).startswith(f"{self.package}."))

    @contextmanager
    def including(self, entries: Iterable[T]) -> Iterator[None]:
        """The block with ``entries`` registered where this process has none of their name (a
        worker handed another process's ``foreign`` entries), removed after it."""
        with ExitStack() as stack:
            for entry in entries:
                if entry.name not in self:
                    stack.enter_context(self.registered(entry))
            yield

    def get(self, name: str) -> T:
        """The entry of a name.

        Raises:
            UnknownEntry: no entry has it (the message lists those that do).
        """
        self._load()
        if name not in self._entries:
            raise UnknownEntry(self.kind, name, self.names())
        return self._entries[name]

    def __contains__(self, name: object) -> bool:
        self._load()
        return name in self._entries

    def entries(self) -> tuple[T, ...]:
        """Every entry, by order, then name."""
        self._load()
        return tuple(sorted(self._entries.values(), key=lambda e: (e.order, e.name)))

    def names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.entries())

    def digest(self) -> str:
        """SHA-256 of the entries' names and their modules' source: what a stage's cache key
        takes, so that a method added or changed redoes the batches it would change."""
        digest = hashlib.sha256()
        for entry in self.entries():
            digest.update(entry.name.encode())
            source = _module_file(entry)
            if source is not None:
                digest.update(Path(source).read_bytes())
        return digest.hexdigest()

    def _load(self) -> None:
        if self._loaded:
            return
        self._loaded = True
        package = importlib.import_module(self.package)
        for module in pkgutil.iter_modules(package.__path__):
            if not module.name.startswith("_"):
                importlib.import_module(f"{self.package}.{module.name}")


def _module_file(entry: object) -> str | None:
    """The file of the module that made an entry (its ``module`` field, where it has one)."""
    name = getattr(entry, "module", None)
    if not isinstance(name, str) or not name:
        return None
    module = importlib.import_module(name)
    return getattr(module, "__file__", None)
