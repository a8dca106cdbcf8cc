"""Continual-learning methods, by name (:mod:`drago.continual.registry`)."""

from __future__ import annotations

import drago.config as _config
from drago.config import METHOD_SETTINGS, Config, ConfigError, setting_value
from drago.continual.base import ContinualMethod, TaskState
from drago.continual.curiosity import Curiosity
from drago.continual.drago import Drago, DragoNoRehearsal, DragoNoReviewer, DragoSingleAgent, PseudoRehearsal
from drago.continual.ewc import EWC
from drago.continual.naive import Continual, LearnerOnly, Scratch
from drago.continual.registry import METHODS, get_method, methods, plugin_problems, register_method
from drago.continual.registry import load_plugins as _load_plugins
from drago.continual.replay import Replay

for _builtin in (Continual, Scratch, Drago, DragoNoRehearsal, DragoNoReviewer, DragoSingleAgent, PseudoRehearsal,
                 EWC, Replay, Curiosity):
    register_method(_builtin.name, _builtin)
# A method.NAME override may be a plug-in method's own setting: the config looks after the plug-ins load.
_config.load_method_plugins = _load_plugins
_config.methods_reads = lambda: {name: method.reads for name, method in METHODS.items()}


def available_methods() -> list[str]:
    return list(methods())


def check_method(cfg: Config) -> Config:
    """``cfg``, once its method is known to exist and to run with these settings
    (:meth:`ContinualMethod.config_problem`; :func:`drago.config.validate` checks everything else).

    Raises:
        ConfigError: an unknown method, or one that cannot run with ``cfg`` (one line).
    """
    problem = get_method(cfg.method.name).config_problem(cfg)
    if problem is not None:
        raise ConfigError(f"method '{cfg.method.name}' {problem}")
    declared = METHOD_SETTINGS.get(cfg.method.name, {})
    for name, value in cfg.method.options.items():
        if name not in declared:
            own = ", ".join(f"method.{n}" for n in declared) or "none"
            raise ConfigError(f"method '{cfg.method.name}' has no setting '{name}' (its own settings: {own}); "
                              "remove it from cfg.method.options")
        cfg.method.options[name] = setting_value(value, declared[name].kind, f"method.{name}")
    return cfg


def build_method(cfg, spec, device) -> ContinualMethod:
    """The configured method, or only its learner when ``transfer.learner_only`` is set."""
    cls = get_method(cfg.method.name)
    if cfg.transfer.learner_only:
        return LearnerOnly(cfg, spec, device, fresh_world_model=cls.fresh_world_model)
    return cls(cfg, spec, device)


__all__ = ["METHODS", "ContinualMethod", "LearnerOnly", "TaskState", "available_methods", "build_method", "check_method",
           "get_method", "methods", "plugin_problems", "register_method"]
