"""The model registry: every zoo network registers under a name; configs refer to it by name."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

from datamodules.errors import ConfigError

if TYPE_CHECKING:  # the nets import this module to register themselves: the base class is for annotations only
    from zoo.nets.base import TrajectoryNet

_MODELS: dict[str, type[TrajectoryNet]] = {}
_Net = TypeVar("_Net", bound="TrajectoryNet")


def register_model(name: str) -> Callable[[type[_Net]], type[_Net]]:
    """Class decorator: make a :class:`~zoo.nets.base.TrajectoryNet` available as ``get_model(name)``."""

    def decorate(cls: type[_Net]) -> type[_Net]:
        if name in _MODELS and _MODELS[name] is not cls:
            raise ValueError(f"model name {name!r} is already registered by {_MODELS[name].__qualname__}")
        cls.model_name = name
        _MODELS[name] = cls
        return cls

    return decorate


def _load_zoo() -> None:
    import zoo.nets  # noqa: F401  (registers the built-in networks)


def model_class(name: str) -> type[TrajectoryNet]:
    """The class registered as ``name``; the error lists the known names."""
    _load_zoo()
    try:
        return _MODELS[name]
    except KeyError:
        raise ConfigError(f"unknown model {name!r}; known models: {', '.join(list_models())}") from None


def get_model(name: str, **kwargs: Any) -> TrajectoryNet:
    """Build the network registered as ``name`` with ``kwargs`` (an argument it does not take: ConfigError)."""
    import inspect

    cls = model_class(name)
    try:
        inspect.signature(cls).bind(**kwargs)
    except TypeError as error:
        known = ", ".join(p for p in inspect.signature(cls).parameters if p not in ("args", "kwargs"))
        raise ConfigError(f"model {name!r}: {error} (net_kwargs); its arguments: {known}") from None
    return cls(**kwargs)


def list_models() -> list[str]:
    """Names of all registered networks, sorted."""
    _load_zoo()
    return sorted(_MODELS)
