"""The one registry pattern of aermani's extension points (segmenters, camera sources, VLM backends): an
implementation is one module whose class carries a name and `@registry.register`; a setting picks it."""

from __future__ import annotations

from typing import Generic, TypeVar

T = TypeVar("T", bound=type)


class Registry(dict[str, T], Generic[T]):
    """Implementations by name, in registration order (a dict, so tests may add and remove entries)."""

    def __init__(self, what: str, attr: str, setting: str, error: type[Exception]) -> None:
        super().__init__()
        self.what = what
        """What the entries are, for messages ("camera source")."""
        self.attr = attr
        """The class attribute holding an entry's name (`type`, `kind`)."""
        self.setting = setting
        """The environment variable that chooses one (named in errors)."""
        self.error = error

    def register(self, cls: T) -> T:
        """Class decorator: make `cls` selectable by its name attribute."""
        name = getattr(cls, self.attr, "")
        if not name:
            raise ValueError(f"{cls.__name__} has no `{self.attr}`")
        self[name] = cls
        return cls

    def lookup(self, name: str) -> T:
        """The class registered as `name`, or the registry's error naming the setting and the choices."""
        cls = self.get(name)
        if cls is None:
            raise self.error(f"unknown {self.what} {name!r}; set {self.setting} to one of {', '.join(self)}")
        return cls
