"""Named choices of the registration: its losses, optimisers and search coordinates.

Each :class:`Registry` declares its names here, in a module that imports nothing heavy (the
command line and the options read them), and the module that implements them fills it with
``@REGISTRY.register(name)`` when it is first imported. ``LOSSES.get("invariant")`` imports that
module on demand.

>>> OPTIMIZERS.check("nelder-mead")
'nelder-mead'
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator
from typing import Any, Generic, TypeVar

__all__ = ["Registry", "LOSSES", "OPTIMIZERS", "PARAMETRIZATIONS"]

T = TypeVar("T", bound=Callable[..., Any])


class Registry(Generic[T]):
    """Factories of one kind, by name.

    Parameters
    ----------
    kind : str
        What the entries are, for messages ("loss", "optimizer").
    names : tuple of str
        Every name the registry holds, in the order messages list them.
    module : str
        The module that registers the entries.
    """

    def __init__(self, kind: str, names: tuple[str, ...], module: str) -> None:
        self.kind = kind
        self.names = names
        self.module = module
        self._entries: dict[str, T] = {}

    def __contains__(self, name: object) -> bool:
        return name in self.names

    def __iter__(self) -> Iterator[str]:
        return iter(self.names)

    def check(self, name: str) -> str:
        """``name`` itself; ValueError naming the choices when it is not one of them."""
        if name not in self.names:
            raise ValueError(f"unknown {self.kind} {name!r}; choose one of {', '.join(self.names)}")
        return name

    def register(self, name: str) -> Callable[[T], T]:
        """A decorator that files a factory under ``name``, a declared name."""
        if name not in self.names:
            raise ValueError(f"{name!r} is not a declared {self.kind} name ({', '.join(self.names)})")

        def file(factory: T) -> T:
            self._entries[name] = factory
            return factory

        return file

    def get(self, name: str) -> T:
        """The factory called ``name``; ValueError for an unknown name."""
        self.check(name)
        if name not in self._entries:
            importlib.import_module(self.module)
        try:
            return self._entries[name]
        except KeyError:
            raise LookupError(f"{self.module} registers no {self.kind} {name!r}") from None


LOSSES: Registry[Callable[..., Any]] = Registry(
    "loss",
    ("invariant", "invariant-paper", "invariant-parts", "correlation", "squared", "silhouette-iou",
     "mutual-information"),
    "vehicle_pose.loss.alternatives",
)
"""Losses: ``factory(target: PhotoTarget) -> callable(Frame) -> float`` (lower is better)."""

OPTIMIZERS: Registry[Callable[..., Any]] = Registry(
    "optimizer", ("nelder-mead", "powell", "cma-es"), "vehicle_pose.search.optimize")
"""Optimisers: ``factory() -> Optimizer``."""

PARAMETRIZATIONS: Registry[Callable[..., Any]] = Registry(
    "parametrization", ("theta", "view"), "vehicle_pose.geometry.parametrize")
"""Search coordinates: ``factory(reference: Camera, frame: SearchFrame) -> Parametrization``."""
