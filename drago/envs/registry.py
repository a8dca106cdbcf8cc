"""The registry of domains: built-ins, your own (:func:`register_domain`), plug-ins found through the
``drago.domains`` entry points, and two families resolved by name: ``dmc:`` (every stock dm_control task)
and ``gym:`` (every registered gymnasium id).

Plug-ins are loaded on the first lookup (:func:`get_domain`, :func:`available_domains`,
:func:`is_domain`, :func:`plugin_problems`). An entry point may load a :class:`~drago.envs.domain.Domain`, a
zero-argument callable returning one, or a module that registers its domains on import. A plug-in that
fails is skipped with one warning line on stderr naming the entry point and its package; the failures
stay available as :func:`plugin_problems`.
"""

from __future__ import annotations

import re
import threading
from collections.abc import Callable
from types import ModuleType
from typing import Any

from drago.envs.builtin import BUILTIN_DOMAINS
from drago.envs.domain import Domain, DomainError
from drago.plugins import PluginProblem, load_entry_points, one_line, package_of

__all__ = ["ENTRY_POINT_GROUP", "PluginProblem", "available_domains", "domain_families", "get_domain", "is_domain",
           "load_plugins", "plugin_problems", "register_domain", "source_of", "unregister_domain"]

#: The entry-point group a package lists its domains under.
ENTRY_POINT_GROUP = "drago.domains"

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")


class _Registry:
    def __init__(self) -> None:
        self.domains: dict[str, Domain] = {}
        self.sources: dict[str, str] = {}
        self.resolved: dict[str, Domain] = {}  # dmc:/gym: domains built on lookup
        self.problems: list[PluginProblem] = []
        self.plugins_loaded = False
        self.loading_source: str | None = None  # set while a plug-in loads: who registers
        self.lock = threading.RLock()


_registry = _Registry()


# ------------------------------------------------------------------------------------------------
# Families: names resolved on lookup
# ------------------------------------------------------------------------------------------------
def _dmc_module():
    try:
        from drago.envs import dmc
    except ImportError as err:
        raise DomainError(f"dmc: domains need dm_control, which is not installed: pip install -e '.[dmc]' "
                          f"(scripts/setup.sh installs it) [{one_line(err, 120)}]") from None
    return dmc


def _dmc_problem(name: str) -> str | None:
    return _dmc_module().stock_problem(name)


def _dmc_build(name: str) -> Domain:
    return _dmc_module().stock_domain(name)


def _gym_problem(name: str) -> str | None:
    from drago.envs.gym_envs import gym_family_problem

    return gym_family_problem(name)


def _gym_build(name: str) -> Domain:
    from drago.envs.gym_envs import gym_family_domain

    return gym_family_domain(name)


#: prefix -> (one line for `drago list`, problem(name) -> str | None, build(name) -> Domain).
_FAMILIES: dict[str, tuple[str, Callable[[str], str | None], Callable[[str], Domain]]] = {
    "dmc:": ("every stock dm_control suite task: dmc:DOMAIN (e.g. dmc:hopper, tasks hopper-stand, hopper-hop); needs "
             + "dm_control", _dmc_problem, _dmc_build),
    "gym:": ("a registered gymnasium id with its own reward: gym:ID (e.g. gym:Pendulum-v1, task Pendulum-v1)",
             _gym_problem, _gym_build),
}


def _family(name: str) -> str | None:
    for prefix in _FAMILIES:
        if name.startswith(prefix):
            return prefix
    return None


def domain_families() -> dict[str, str]:
    """The name families resolved on lookup (prefix -> one line), which :func:`available_domains` omits."""
    return {prefix: line for prefix, (line, _, _) in _FAMILIES.items()}


# ------------------------------------------------------------------------------------------------
# Registration
# ------------------------------------------------------------------------------------------------
def register_domain(domain: Domain, replace: bool = False) -> Domain:
    """Make a domain available by its name to ``make_env``, configs (``env.domain=NAME``) and the CLI.

    Args:
        domain: The domain (see :func:`~drago.envs.gym_envs.gym_domain` to build one from gymnasium envs).
        replace: Replace a domain already registered under that name instead of refusing.

    Returns:
        The domain itself.

    Raises:
        DomainError: Not a Domain, a bad name, or a name already taken (one line).
    """
    if not isinstance(domain, Domain):
        raise DomainError(f"register_domain takes a drago.envs.Domain, got {type(domain).__name__}; build one "
                          "with Domain(...) or gym_domain(...)")
    name = domain.name
    if not _NAME.fullmatch(name):
        prefix = _family(name)
        reserved = f"; the prefix {prefix} is reserved for its family" if prefix else ""
        raise DomainError(f"bad domain name {name!r}: use letters, digits, '_', '.' and '-', starting with a "
                          f"letter or digit{reserved}")
    with _registry.lock:
        if name in _registry.domains and not replace:
            how = ("give the entry point another name" if _registry.loading_source  # it cannot pass replace=True
                   else "choose another name or pass replace=True")
            raise DomainError(f"domain '{name}' is already registered ({_registry.sources[name]}); {how}")
        _registry.domains[name] = domain
        _registry.sources[name] = _registry.loading_source or "register_domain"
    return domain


def unregister_domain(name: str) -> None:
    """Remove a registered domain (KeyError-free: a name not registered is ignored)."""
    with _registry.lock:
        _registry.domains.pop(name, None)
        _registry.sources.pop(name, None)


# ------------------------------------------------------------------------------------------------
# Plug-ins
# ------------------------------------------------------------------------------------------------
def _load_entry_point(ep: Any) -> None:
    """Load one entry point and register what it gives; raises on any problem."""
    obj = ep.load()
    if isinstance(obj, ModuleType):
        return  # a module that registers its domains on import
    if not isinstance(obj, Domain):
        if not callable(obj):
            raise DomainError(f"it loads a {type(obj).__name__}, not a drago.envs.Domain or a callable returning one")
        made = obj()
        if not isinstance(made, Domain):
            raise DomainError(f"its callable returned a {type(made).__name__}, not a drago.envs.Domain")
        obj = made
    register_domain(obj)


def load_plugins(reload: bool = False) -> tuple[PluginProblem, ...]:
    """Load the domains of the ``drago.domains`` entry points (once; lookups call this themselves).

    Args:
        reload: Forget the plug-ins loaded before (their domains are unregistered) and look again.

    Returns:
        The plug-ins that were skipped, as :func:`plugin_problems` does.
    """
    with _registry.lock:
        if reload:
            for name in [n for n, source in _registry.sources.items() if source.startswith("entry point")]:
                unregister_domain(name)
            _registry.problems.clear()
            _registry.plugins_loaded = False
        if _registry.plugins_loaded:
            return tuple(_registry.problems)
        _registry.plugins_loaded = True  # before loading: a plug-in that looks domains up must not recurse

        def register(ep: Any) -> None:
            _registry.loading_source = f"entry point '{ep.name} = {ep.value}' of package '{package_of(ep)}'"
            try:
                _load_entry_point(ep)
            finally:
                _registry.loading_source = None

        _registry.problems.extend(load_entry_points(ENTRY_POINT_GROUP, "domain", register,
                                                    plain_errors=(DomainError,)))
        return tuple(_registry.problems)


def plugin_problems() -> tuple[PluginProblem, ...]:
    """The domain plug-ins that failed to load and were skipped (each one line as ``str(problem)``)."""
    return load_plugins()


# ------------------------------------------------------------------------------------------------
# Lookup
# ------------------------------------------------------------------------------------------------
def available_domains() -> tuple[str, ...]:
    """The registered domains' names: built-ins first, then in registration order. The ``dmc:`` and
    ``gym:`` families (:func:`domain_families`) are not listed."""
    load_plugins()
    with _registry.lock:
        return tuple(_registry.domains)


def _unknown(name: object) -> DomainError:
    valid = ", ".join([*_registry.domains, *(f"{p}..." for p in _FAMILIES)])
    return DomainError(f"unknown domain '{name}'; valid domains: {valid}")


def get_domain(name: str) -> Domain:
    """The domain of that name; ``dmc:`` and ``gym:`` names are built on first lookup.

    Raises:
        DomainError: An unknown name (one line listing the valid ones).
    """
    load_plugins()
    with _registry.lock:
        if isinstance(name, str) and name in _registry.domains:
            return _registry.domains[name]
        prefix = _family(name) if isinstance(name, str) else None
        if prefix is None:
            raise _unknown(name)
        if name not in _registry.resolved:
            _registry.resolved[name] = _FAMILIES[prefix][2](name)
        return _registry.resolved[name]


def is_domain(name: str) -> bool:
    """True for a registered domain and for a valid ``dmc:`` or ``gym:`` name (checked without building an
    env; a ``dmc:`` name imports dm_control, and is False without it)."""
    load_plugins()
    if not isinstance(name, str):
        return False
    with _registry.lock:
        if name in _registry.domains or name in _registry.resolved:
            return True
    prefix = _family(name)
    if prefix is None:
        return False
    try:
        return _FAMILIES[prefix][1](name) is None
    except DomainError:
        return False


def source_of(name: str) -> str | None:
    """Who registered a domain: ``built-in``, ``register_domain`` or the entry point and package."""
    load_plugins()
    return _registry.sources.get(name)


def _register_builtins() -> None:
    for domain in BUILTIN_DOMAINS:
        register_domain(domain)
        _registry.sources[domain.name] = "built-in"


_register_builtins()
