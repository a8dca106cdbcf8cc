"""Continual-learning methods, by name."""

from __future__ import annotations

from drago.config import Config, ConfigError
from drago.continual.base import ContinualMethod, TaskState
from drago.continual.curiosity import Curiosity
from drago.continual.drago import Drago, DragoNoRehearsal, DragoNoReviewer, DragoSingleAgent, PseudoRehearsal
from drago.continual.ewc import EWC
from drago.continual.naive import Continual, LearnerOnly, Scratch
from drago.continual.replay import Replay

METHODS: dict[str, type[ContinualMethod]] = {
    "continual": Continual,
    "scratch": Scratch,
    "drago": Drago,
    "drago-no-rehearsal": DragoNoRehearsal,
    "drago-no-reviewer": DragoNoReviewer,
    "drago-single-agent": DragoSingleAgent,
    "pseudo-rehearsal": PseudoRehearsal,
    "ewc": EWC,
    "replay": Replay,
    "curiosity": Curiosity,
}


def available_methods() -> list[str]:
    return list(METHODS)


def get_method(name: str) -> type[ContinualMethod]:
    """The method class of a name.

    Raises:
        ConfigError: an unknown name (one line listing the valid ones).
    """
    if name not in METHODS:
        raise ConfigError(f"unknown method '{name}'; valid methods: {', '.join(METHODS)}")
    return METHODS[name]


def check_method(cfg: Config) -> Config:
    """``cfg``, once its method is known to exist (:func:`drago.config.validate` checks everything else).

    Raises:
        ConfigError: an unknown method.
    """
    get_method(cfg.method.name)
    return cfg


def build_method(cfg, spec, device) -> ContinualMethod:
    """The configured method, or only its learner when ``transfer.learner_only`` is set."""
    cls = get_method(cfg.method.name)
    if cfg.transfer.learner_only:
        return LearnerOnly(cfg, spec, device, fresh_world_model=cls.fresh_world_model)
    return cls(cfg, spec, device)


__all__ = ["METHODS", "ContinualMethod", "LearnerOnly", "TaskState", "available_methods", "build_method",
           "check_method", "get_method"]
