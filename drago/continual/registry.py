"""The method registry: the built-in methods, methods registered from Python, and plug-ins from packages.

A method is a :class:`~drago.continual.base.ContinualMethod` subclass registered under a name, with
``@drago.register_method("my-method")`` or through a package's entry point in the group ``drago.methods``
(docs: Extending drago). Plug-ins load on the first lookup; one that fails to load is skipped with one
warning line naming it and its package, and drago runs on with the rest.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import fields
from typing import Any, TypeVar

from drago.config import METHOD_SETTINGS, ConfigError, MethodConfig, MethodSetting, setting_value
from drago.continual.base import ContinualMethod
from drago.plugins import PluginProblem, load_entry_points, package_of

ENTRY_POINT_GROUP = "drago.methods"
NAME = re.compile(r"[a-z0-9][a-z0-9_-]*")

M = TypeVar("M", bound=type[ContinualMethod])

#: The live registry, name -> class; add to it with :func:`register_method` (tests may patch it).
METHODS: dict[str, type[ContinualMethod]] = {}
#: The package each plug-in method came from, by name (built-in and register_method ones are absent).
METHOD_PACKAGES: dict[str, str] = {}
_problems: list[PluginProblem] = []
_plugins_loaded = False


class RegistryError(ConfigError):
    """A method that cannot be registered as asked; the message is one line."""


def register_method(name: str, cls: M | None = None, *, replace: bool = False) -> Any:
    """Register a :class:`ContinualMethod` subclass under ``name``; a decorator when ``cls`` is omitted.

    Example::

        @drago.register_method("l2-anchor")
        class L2Anchor(drago.ContinualMethod):
            ...

    Raises:
        RegistryError: a name that is not lowercase letters, digits, ``-`` and ``_``; a class that is not a
            ContinualMethod subclass; a name another class holds (pass ``replace=True`` to take it over).
    """
    def add(method: M) -> M:
        if not isinstance(name, str) or not NAME.fullmatch(name):
            raise RegistryError(f"method name {name!r} must be lowercase letters, digits, '-' and '_', "
                                "starting with a letter or digit")
        if not (isinstance(method, type) and issubclass(method, ContinualMethod)):
            raise RegistryError(f"register_method({name!r}): {method!r} is not a subclass of "
                                "drago.ContinualMethod; derive the method from it")
        held = METHODS.get(name)
        if held is not None and held is not method and not replace:
            raise RegistryError(f"method '{name}' is already registered by {_where(held)}; choose another name "
                                "or pass replace=True")
        _check_settings(name, method)
        METHODS[name] = method
        if method.settings:
            METHOD_SETTINGS[name] = dict(method.settings)
        else:
            METHOD_SETTINGS.pop(name, None)
        return method

    return add if cls is None else add(cls)


def _check_settings(name: str, method: type[ContinualMethod]) -> None:
    """A method's own settings: MethodSetting values of a plain type, under names no built-in setting has."""
    builtin = {f.name for f in fields(MethodConfig)}
    for key, setting in method.settings.items():
        if not isinstance(setting, MethodSetting) or setting.kind not in (int, float, bool, str):
            raise RegistryError(f"method '{name}': its setting '{key}' must be a drago.MethodSetting of kind int, "
                                "float, bool or str")
        if key in builtin or not NAME.fullmatch(key.replace("-", "_")) or "-" in key:
            raise RegistryError(f"method '{name}': its setting name '{key}' is taken by a built-in setting or is not "
                                "a lowercase identifier; rename it")
        try:
            setting_value(setting.default, setting.kind, f"method.{key}")
        except ConfigError as err:
            raise RegistryError(f"method '{name}': the default of {err}") from None


def _where(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def load_plugins(entries: Callable[..., Any] | None = None) -> None:
    """Register the methods of every installed plug-in (entry point group ``drago.methods``), once.

    An entry point names a ContinualMethod subclass (registered under the entry point's name) or a module
    whose import registers its methods. A failure is recorded, announced on stderr in one line, and skipped.
    """
    global _plugins_loaded
    if _plugins_loaded:
        return
    _plugins_loaded = True

    def register(entry: Any) -> None:
        if entry.name in METHODS:  # an entry point cannot pass replace=True: its name must change
            raise RegistryError(f"method '{entry.name}' is already registered by {_where(METHODS[entry.name])}; "
                                "give the entry point another name")
        loaded = entry.load()
        if isinstance(loaded, type):
            register_method(entry.name, loaded)
        elif entry.name not in METHODS:
            raise RegistryError(f"it loaded {entry.value} but registered no method named '{entry.name}'")
        METHOD_PACKAGES[entry.name] = package_of(entry)

    _problems.extend(load_entry_points(ENTRY_POINT_GROUP, "method", register, plain_errors=(ConfigError,),
                                       entries=entries))


def methods() -> dict[str, type[ContinualMethod]]:
    """Every registered method by name: the built-in ones first, then plug-ins."""
    load_plugins()
    return dict(METHODS)


def plugin_problems() -> list[PluginProblem]:
    """The method plug-ins that failed to load and were skipped (each one line as ``str(problem)``)."""
    load_plugins()
    return list(_problems)


def get_method(name: str) -> type[ContinualMethod]:
    """The method class of a name.

    Raises:
        ConfigError: an unknown name (one line listing the valid ones).
    """
    found = methods()
    if name not in found:
        raise ConfigError(f"unknown method '{name}'; valid methods: {', '.join(found)}")
    return found[name]
