"""Lazy imports: :class:`later`, a stage's function imported on its first call (the command line's stage
functions, the engine's colouring), so that importing a module that binds it loads nothing more."""

from __future__ import annotations

from importlib import import_module
from typing import Any


class later:  # noqa: N801 (reads as the import statement it stands for)
    """``name = later("organlab.module", "name")``: ``from organlab.module import name``, run on the first call.

    The command line binds each stage function it calls this way, so that building its parser
    (``organlab --help``, ``--version``, a mistyped flag) imports no stage, numba or viewer.  Use it at the
    top of a module only, with literal strings: ``tests/test_architecture.py`` reads these lines as the
    imports they are (floors, cycles, underscore names, no import inside a function).

    The name is looked up in its module at every call (nothing cached), so a test that replaces
    ``organlab.module.name`` sees its replacement used, and nothing of it stays behind.

    Parameters
    ----------
    module : str
        Absolute module name, ``"organlab.pipeline"``.
    name : str
        A callable of that module (function or class), ``"reconstruct"``; or a constant, read with
        :meth:`resolve` (the engine's colouring defaults: the default run does not load the colouring).

    Examples
    --------
    >>> from organlab.lazy import later
    >>> printable = later("organlab.validate", "printable")
    >>> printable("a\\nb")
    'a\\\\nb'
    """

    __slots__ = ("module", "name")

    def __init__(self, module: str, name: str) -> None:
        if not (isinstance(module, str) and module.startswith("organlab.") and isinstance(name, str) and name):
            raise ValueError(f"later(module, name): an organlab module and a name, got {module!r}, {name!r}")
        self.module, self.name = module, name

    def resolve(self) -> Any:
        """The object itself (imports its module when not yet imported)."""
        return getattr(import_module(self.module), self.name)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.resolve()(*args, **kwargs)

    def __getattr__(self, attribute: str) -> Any:
        # a class bound this way: ``Reconstruction.load(...)`` (only names not in __slots__ get here)
        if attribute.startswith("__"):
            raise AttributeError(attribute)
        return getattr(self.resolve(), attribute)

    def __repr__(self) -> str:
        return f"later({self.module!r}, {self.name!r})"
