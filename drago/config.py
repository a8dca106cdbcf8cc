"""Typed settings, named presets and ``key=value`` overrides.

Every setting is a documented dataclass field. A preset is a YAML file in ``drago/presets`` that
lists only what differs from the defaults below (optionally on top of another preset via ``base``).
Validation happens once, in :func:`load_config`; every error is a :class:`ConfigError` whose message
is one line naming the bad key or value and the valid choices.

The defaults are the paper's MiniGrid values (paper Appendix A.1) with the official code's behaviour wherever
paper and code disagree (docs: Design, paper and code); each such switch says so in its field comment.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import re
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from drago.envs import available_domains, available_tasks, get_domain, is_domain


class ConfigError(ValueError):
    """A bad preset, key or value; the message is one line meant for the user."""


class _Section:
    """A config section that refuses attributes it does not declare: ``cfg.train.steps_per_taks = 100`` (a
    typo) is an error naming the setting, not a silent no-op."""

    section = ""

    def __setattr__(self, name: str, value: Any) -> None:
        declared = [f.name for f in fields(self)] if dataclasses.is_dataclass(self) else []
        if declared and name not in declared:
            raise ConfigError(_unknown(f"{self.section}.{name}", [key for key, _, _ in _leaves(self, self.section)]))
        object.__setattr__(self, name, value)


def _unknown(key: str, valid: list[str], more: str = "") -> str:
    import difflib

    close = difflib.get_close_matches(key, valid, n=1)
    hint = f"did you mean {close[0]}? " if close else ""
    return f"unknown setting '{key}'; {hint}{more}run `drago list --settings` for the valid keys"


@dataclass(frozen=True)
class MethodSetting:
    """A setting a plug-in method declares (``ContinualMethod.settings``; docs: Extending drago, "Settings of
    your own"): set as ``method.NAME=value`` like a built-in one, kept in ``cfg.method.options``.

    Attributes:
        kind: ``int``, ``float``, ``bool`` or ``str``.
        default: its value when nothing sets it.
        description: one line, shown by ``drago list --settings``.
    """

    kind: type
    default: Any
    description: str


#: The settings each method with settings of its own declares, by method name (filled as methods register).
METHOD_SETTINGS: dict[str, dict[str, MethodSetting]] = {}
#: Called before a method's own settings are looked up, so that plug-in methods have registered (the
#: continual layer installs it: settings sit below the methods that read them).
load_method_plugins: Callable[[], None] = lambda: None
#: Called before ``agent.kind`` is checked, so that plug-in agent kinds have registered (the agent layer
#: installs it, and registering a kind adds its name to ``CHOICES["agent.kind"]``).
load_agent_plugins: Callable[[], None] = lambda: None


@dataclass
class EnvConfig(_Section):
    """Which world and which sequence of tasks."""

    # minigrid, cheetah or walker (DeepMind Control; needs the dmc extra), a registered domain (`drago list`),
    # or dmc:DOMAIN for a stock DeepMind Control domain (docs: Environments and tasks)
    domain: str = "minigrid"
    tasks: tuple[str, ...] = ("room1", "room2", "room3", "room4")  # the continual sequence, in order
    dense_reward: bool | None = None  # grid only; None: each task's own default (training dense, test tasks sparse)
    episode_length: int = 100  # agent steps per episode
    action_repeat: int = 1  # simulator control steps per agent step, rewards summed (grid 1, cheetah 4, walker 2)


@dataclass
class TdmpcConfig(_Section):
    """TD-MPC as modified in DRAGO (paper §2; docs: Design, the agent): read when ``agent.kind=tdmpc``."""

    mlp_dim: int = 512  # hidden width of every network (world model, heads, critics)
    use_crelu: bool = True  # CReLU dynamics as at the code's HEAD; the paper-era run used ELU (false)
    horizon: int = 10  # training and maximum planning horizon H
    discount: float = 0.99  # gamma of the TD targets and of the planner's returns
    # None: a constant lr (paper and code). Otherwise every optimizer of a task decays linearly agent.lr -> lr_final
    # over its first lr_schedule_steps task steps; optimizers start afresh with each task (paper §3.3; docs: Design, how a run flows).
    lr_final: float | None = None
    lr_schedule_steps: int = 300_000  # task steps over which lr decays to lr_final (see lr_final)
    rho: float = 0.5  # temporal weight of the t-th loss term
    consistency_coef: float = 2.0  # weight of the latent consistency loss
    reward_coef: float = 0.5  # weight of the reward loss
    value_coef: float = 0.1  # weight of the TD value loss
    grad_clip_norm: float = 10.0  # gradient norm clip of every update
    tau: float = 0.01  # target EMA coefficient (the paper's table calls it "temperature")
    update_freq: int = 40  # target EMA every this many gradient steps
    first_step_qr_only: bool = False  # true: reward and value losses at t=0 only (code: DMC true, grid false)
    # Planning (paper §2; docs: Design, the agent).
    iterations: int = 6  # CEM iterations per planned action
    num_samples: int = 512  # action sequences sampled per CEM iteration
    num_elites: int = 64  # best sequences that refit the CEM distribution
    mixture_coef: float = 0.05  # fraction of policy trajectories added to the sampled ones
    temperature: float = 0.5  # softmax temperature of the elites' weights
    momentum: float = 0.1  # weight of the previous CEM mean in each refit
    min_std: float = 0.05  # final CEM std floor (see std_schedule_start)
    max_std: float = 2.0  # initial CEM std of continuous actions
    use_q: bool = True  # terminal Q value in the planner's return
    elite_selection: str = "sample"  # code: sample an elite in proportion to its weight; paper: argmax
    horizon_schedule_steps: int = 10_000  # planning horizon grows linearly 1 -> H over these task steps
    std_schedule_start: float = 0.5  # CEM std floor, linear start -> min_std over std_schedule_steps
    std_schedule_steps: int = 50_000  # task steps over which the CEM std floor falls to min_std
    # Speed (docs: Speed and precision). A run resolves each `auto` on the machine it starts on and writes the
    # choice into its config.yaml (drago.agent.speed). bfloat16: autocast of the networks' hidden layers in
    # updates and planning; output layers, losses, TD targets and optimizer state stay float32.
    precision: str = "auto"  # auto, float32 or bfloat16
    compile: str = "auto"  # auto, true or false: torch.compile the update's losses and the planner's step
    # The heads' tanh (critics, policy mean) as 2*sigmoid(2x) - 1: within 3e-7 of torch.tanh, faster on
    # CPUs where torch.tanh is not vectorised (docs: Speed and precision); false gives torch.tanh's bits.
    fast_tanh: bool = True


@dataclass
class PetsAgentConfig(_Section):
    """PETS (Chua et al. 2018; docs: Methods, PETS), a probabilistic ensemble and CEM over action sequences:
    read when ``agent.kind=pets``."""

    members: int = 5  # ensemble size E
    hidden: int = 200  # width of every hidden layer of the ensemble (and of the learned reward)
    layers: int = 4  # hidden layers of each ensemble member
    particles: int = 20  # particles per action sequence; a multiple of members spreads them evenly
    propagation: str = "tsinf"  # tsinf: a particle keeps its member for the whole horizon; ts1: redrawn each step
    horizon: int = 25  # planning horizon in agent steps
    iterations: int = 5  # CEM iterations per planned action
    population: int = 400  # action sequences per CEM iteration
    elites: int = 40  # best sequences that refit the CEM distribution
    momentum: float = 0.1  # weight of the previous CEM mean in each refit
    # learned: each agent learns r(s, a, s') with a head of its own; known: the learner plans on the task's
    # true reward (a domain that declares it, as the grid; DRAGO's reviewer still learns its intrinsic reward)
    reward: str = "learned"


@dataclass
class AgentConfig(_Section):
    """The agent: what every kind reads, then one section per built-in kind (agent.tdmpc, agent.pets); a run reads
    the section of its ``kind`` only."""

    # tdmpc: TD-MPC, the paper's agent; pets: PETS, the agent of the paper's Appendix E; or a registered plug-in
    # kind (`drago list` shows them)
    kind: str = "tdmpc"
    lr: float = 1e-3  # Adam learning rate of every optimizer (world model, heads, DRAGO's generator)
    batch_size: int = 512  # training sequences (TD-MPC: of H+1 steps) per gradient step
    seed_steps: int = 5_000  # random actions (and no updates) for this many agent steps of each task
    # What the horizon, std-floor, lr and target-EMA schedules count: "task", a task's agent steps with DRAGO's
    # reviewer's (the official code's clock), or "learner", the learner's alone; the same for reviewer-less methods.
    schedule_clock: str = "task"
    # Seed-phase probabilities of a discrete domain's actions, used when there is one per action (the grid's
    # left, right, forward); other discrete domains, or an empty list, draw uniformly.
    random_action_probs: tuple[float, ...] = (0.2, 0.2, 0.6)
    per_alpha: float = 0.6  # prioritized replay: priority exponent
    per_beta: float = 0.4  # prioritized replay: importance-weight exponent
    tdmpc: TdmpcConfig = field(default_factory=TdmpcConfig)
    pets: PetsAgentConfig = field(default_factory=PetsAgentConfig)


@dataclass
class TrainConfig(_Section):
    """Budgets, evaluation, checkpoints and the machine."""

    steps_per_task: int = 300_000  # agent steps per task, learner and reviewer together (the code's count)
    # Separate budgets instead, when either is set: a task ends after learner_steps_per_task learner steps
    # (None: steps_per_task) and DRAGO's reviewer collects up to reviewer_steps_per_task (None: as many).
    learner_steps_per_task: int | None = None
    reviewer_steps_per_task: int | None = None  # DRAGO's reviewer's own budget a task (see learner_steps_per_task)
    updates_per_episode: int | None = None  # gradient steps after each iteration; None: episode_length
    eval_freq: int = 10_000  # evaluate every this many env steps of a task (and at its start and end)
    # Evaluate every this many learner episodes instead (eval_freq is then unused); transfer runs use it.
    eval_every_episodes: int | None = None
    eval_episodes: int = 10  # episodes of each evaluation, played side by side
    checkpoint_freq: int = 50_000  # periodic resumable checkpoint every this many env steps
    # DMC only: at the end of each task, episodes of the final learner (eval mode, own seeds and env) whose
    # transitions are saved to heldout/task<k>_<name>.npz, never trained on; `drago eval heldout` scores every
    # stage's world model on them (the retention matrix). 0: none.
    heldout_episodes: int = 4
    seed: int = 1  # the run's seed: same seed, same CPU, same logs
    device: str = "cpu"  # cpu, cuda, cuda:N
    threads: int = 0  # torch intra-op threads; 0: all cores
    tensorboard: bool = True  # also write TensorBoard events (the CSV logs are always written)
    # W&B tracking (docs: Command line and configs, Experiment tracking). off, online or offline (written
    # locally, `wandb sync` later): also send TensorBoard's scalars and the whole config to Weights & Biases;
    # needs the wandb extra (pip install 'drago[wandb]'). A resumed run continues its W&B run.
    wandb: str = "off"
    wandb_project: str = "drago"  # the W&B project
    wandb_entity: str | None = None  # the W&B user or team; None: your default entity
    wandb_group: str | None = None  # a W&B group for the run (e.g. a study's name); None: no group
    wandb_tags: tuple[str, ...] = ()  # W&B tags of the run
    wandb_name: str | None = None  # the W&B run name; None: PRESET/METHOD/seedS


@dataclass
class VaeConfig(_Section):
    """DRAGO's generative model over (observation, action) (paper §3.1)."""

    hidden_dim: int = 64  # code: 64 grid, 256 DMC (the paper's "vae latent dim")
    latent_dim: int = 64  # latent width of the VAE
    recon_coef: float = 1.0  # weight of the VAE's reconstruction term
    kl_coef: float = 1.0  # code: 1.0 grid, 0.02 DMC; the paper's table says 0.02
    data: str = "combined"  # combined: reviewer + learner rows (code); learner: learner rows only (paper Alg. 3)


@dataclass
class RehearsalConfig(_Section):
    """DRAGO's synthetic rehearsal (paper §3.1): generated pairs labelled by the previous world model."""

    freq: int = 1  # every this many gradient steps (code: 1 grid, 10 DMC; paper: 10, 20)
    batch: int = 512  # generated (observation, action) pairs per rehearsal step
    mode: str = "separate"  # separate: own optimizer step of weight 1 (code); joint: a weighted term (paper)
    weight: float = 1.0  # weight of the rehearsal term in joint mode (the paper's lambda)
    target: str = "pre_squash"  # pre_squash: raw MLP outputs (code); post_squash: as the planner sees them


@dataclass
class ReviewerConfig(_Section):
    """DRAGO's reviewer and its intrinsic reward (paper §3.2; docs: Design, paper and code)."""

    # code: sigmoid(4(-log MSE_old - theta)) - a*sigmoid(-log MSE_cur - theta); paper: no theta, abs error
    intrinsic_reward: str = "code"
    cost_coef: float = 0.5  # alpha, the weight of the current model's familiarity
    initial_threshold: float = 9.5  # theta of task 2 when the checkpoint has none
    threshold_momentum: float = 0.9  # theta_new <- m * theta_new + (1 - m) * prediction score
    # The reviewer is paid against theta - threshold_offset (code form). 0: the code. theta tracks the score on
    # the learner's own training batches, above the model's score over the room it learned (docs: Reproducing
    # the paper, why the reviewer brings no room back), so r_old pays on few old transitions.
    threshold_offset: float = 0.0
    pseudo_counts: bool = True  # count bonus in reviewer planning (code only, not in the paper)


@dataclass
class EwcConfig(_Section):
    """Elastic weight consolidation on the world model (docs: Methods, EWC)."""

    coef: float = 100.0  # weight of the quadratic penalty on the world model
    fisher_batches: int = 50  # batches of the task's data used to estimate the diagonal Fisher


@dataclass
class ReplayConfig(_Section):
    """A bounded reservoir of old transitions (docs: Methods, replay)."""

    capacity: int = 2163  # transitions kept across tasks; default: the grid VAE's memory (docs: Methods, replay)
    fraction: float = 0.5  # share of world-model rows drawn from the old-task buffer


@dataclass
class CuriosityConfig(_Section):
    """A prediction-error bonus in the learner's TD target (docs: Methods, curiosity)."""

    coef: float = 1.0  # prediction-error bonus added to the learner's TD target


@dataclass
class MethodConfig(_Section):
    """The continual-learning method, then one section per part of the built-in methods; each method reads the
    sections it declares (`drago list --settings` names them)."""

    name: str = "continual"  # the method (`drago list` shows them)
    vae: VaeConfig = field(default_factory=VaeConfig)
    rehearsal: RehearsalConfig = field(default_factory=RehearsalConfig)
    reviewer: ReviewerConfig = field(default_factory=ReviewerConfig)
    ewc: EwcConfig = field(default_factory=EwcConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    curiosity: CuriosityConfig = field(default_factory=CuriosityConfig)
    # The settings a plug-in method declares, by name (method.NAME=value sets one; docs: Extending drago)
    options: dict[str, Any] = field(default_factory=dict)


@dataclass
class TransferConfig(_Section):
    """A test task learned from another run's world model (paper §4.4); see `drago transfer`.

    Unset (the default) in a continual run. `drago transfer` writes these settings into the transfer
    run's config, so `drago resume` continues a transfer like any other run.
    """

    # Task checkpoint (`checkpoints/task<K>_<name>.pt` of another run) whose world model and method state
    # (DRAGO: VAE, threshold) the first task starts from; heads are fresh. Relative to this run's directory.
    checkpoint: str | None = None
    after: int | None = None  # the stage K that checkpoint ends (1-based), for summaries and reports
    # True: the test task is learned by the plain learner, without the method's extras (DRAGO's reviewer,
    # rehearsal and VAE updates; EWC's penalty; ...). False: they keep running, as in the official code.
    learner_only: bool = False
    few_shot_episodes: int = 20  # summary.json reads the few-shot score after this many learner episodes
    # DMC "X2Y" test tasks (paper §4.4, Table 1): every learner and evaluation episode starts with a reset followed by
    # pre_rollout_steps agent steps of the learner saved in this task checkpoint (its heads and world model,
    # eval-mode planning); those steps are neither stored nor counted. Relative to this run's directory.
    pre_rollout_checkpoint: str | None = None
    pre_rollout_steps: int = 100  # agent steps of each pre-rollout (see pre_rollout_checkpoint)
    # source: plan with the horizon and CEM std floor the source learner had at the end of its task;
    # code: the official code's quirk, the test task's horizon schedule (1 early on) and a std floor of 0.5.
    pre_rollout_planning: str = "source"
    case: str | None = None  # the catalogue's test task (e.g. jump2run) this transfer runs, for summaries
    # The reward of the transfers made from this run when `drago transfer` is not told (--reward): dense or
    # sparse; unset, the catalogue's (test tasks sparse). The PETS presets ask for dense (paper Appendix E).
    reward: str | None = None


@dataclass
class Config:
    """Everything one run needs; `preset` records where the values came from."""

    preset: str = "minigrid"
    env: EnvConfig = field(default_factory=EnvConfig)
    agent: AgentConfig = field(default_factory=AgentConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    method: MethodConfig = field(default_factory=MethodConfig)
    transfer: TransferConfig = field(default_factory=TransferConfig)

    def __setattr__(self, name: str, value: Any) -> None:
        if name not in ("preset", *SECTIONS):
            raise ConfigError(f"unknown config section '{name}'; valid sections: preset, {', '.join(SECTIONS)}")
        object.__setattr__(self, name, value)

    def to_dict(self) -> dict[str, Any]:
        return _to_plain(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Config:
        """Rebuild a config written by :meth:`to_dict` (for example a run's ``config.yaml``)."""
        cfg = cls()
        _merge(cfg, migrate_saved(data), "")
        validate(cfg)
        return cfg

    @property
    def updates_per_episode(self) -> int:
        return self.train.updates_per_episode or self.env.episode_length


SECTIONS = ("env", "agent", "train", "method", "transfer")
#: Every section by its dotted name: the five above, then the agent kinds' and the methods' own.
SECTION_CLASSES: dict[str, type] = {
    "env": EnvConfig, "agent": AgentConfig, "agent.tdmpc": TdmpcConfig, "agent.pets": PetsAgentConfig,
    "train": TrainConfig, "method": MethodConfig, "method.vae": VaeConfig, "method.rehearsal": RehearsalConfig,
    "method.reviewer": ReviewerConfig, "method.ewc": EwcConfig, "method.replay": ReplayConfig,
    "method.curiosity": CuriosityConfig, "transfer": TransferConfig}
for _name, _cls in SECTION_CLASSES.items():
    _cls.section = _name  # class attributes, not fields: type.__setattr__ is not the instances' guard
ELITE_SELECTIONS = ("sample", "argmax")
PRECISIONS = ("auto", "float32", "bfloat16")
COMPILE_CHOICES = ("auto", "true", "false")
PRE_ROLLOUT_PLANNING = ("source", "code")
AGENT_KINDS = ("tdmpc", "pets")
INTRINSIC_REWARDS = ("code", "paper")  # the reviewer's reward: the official code's form or the paper's (§3.2)


PRESET_ENTRY_POINT_GROUP = "drago.presets"


def _builtin_presets() -> list[str]:
    root = resources.files("drago") / "presets"
    return sorted(p.name[: -len(".yaml")] for p in root.iterdir() if p.name.endswith(".yaml"))


_plugin_presets: dict[str, tuple[Any, str]] | None = None  # name -> (the YAML file, its package)
_preset_problems: list = []


def plugin_presets() -> dict[str, tuple[Any, str]]:
    """Presets that installed packages ship under the entry-point group ``drago.presets``: by name, the YAML
    file and the package. An entry point loads a path to a YAML file (a ``str``, a ``pathlib.Path`` or an
    ``importlib.resources`` file, or a function returning one); one that fails, or takes a built-in preset's
    name, is skipped with one warning line (docs: Extending drago, "Ship a preset")."""
    global _plugin_presets
    if _plugin_presets is None:
        from drago.plugins import load_entry_points, package_of

        found: dict[str, tuple[Any, str]] = {}
        builtin = set(_builtin_presets())

        def register(entry: Any) -> None:
            target = entry.load()
            target = target() if callable(target) and not hasattr(target, "read_text") else target
            target = Path(target) if isinstance(target, (str, os.PathLike)) else target
            if not hasattr(target, "read_text"):
                raise ConfigError(f"it loads a {type(target).__name__}, not the path of a YAML file")
            if entry.name in builtin or entry.name in found:
                raise ConfigError(f"'{entry.name}' is already a preset's name; give the entry point another name")
            if not target.is_file():
                raise ConfigError(f"its file {target} does not exist")
            found[entry.name] = (target, package_of(entry))

        _preset_problems.extend(load_entry_points(PRESET_ENTRY_POINT_GROUP, "preset", register,
                                                  plain_errors=(ConfigError,)))
        _plugin_presets = found
    return dict(_plugin_presets)


def preset_plugin_problems() -> list:
    """The preset plug-ins that were skipped (each one line as ``str(problem)``)."""
    plugin_presets()
    return list(_preset_problems)


def available_presets() -> list[str]:
    """Names of the presets: those shipped with drago, then those of installed plug-in packages."""
    return [*_builtin_presets(), *sorted(plugin_presets())]


PRESET_SUFFIXES = (".yaml", ".yml")

#: Where a preset's entry came from, for messages: ``where(section, key)`` -> ``"preset NAME: "`` or ``"FILE:LINE: "``.
Where = Callable[[str | None, str | None], str]


def _is_preset_file(ref: str) -> bool:
    return ref.endswith(PRESET_SUFFIXES) or "/" in ref or os.sep in ref


def _yaml_with_lines(text: str, origin: str) -> tuple[Any, dict[tuple[str, str | None], int]]:
    """A YAML document and the 1-based line of each top-level key and of each key below it (by its dotted path
    inside its section, ``("agent", "tdmpc.horizon")``)."""
    try:
        node = yaml.compose(text)
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        line = f":{mark.line + 1}" if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise ConfigError(f"{origin}{line}: not valid YAML ({problem})") from None
    lines: dict[tuple[str, str | None], int] = {}

    def index(section: str, mapping: yaml.MappingNode, prefix: str) -> None:
        for inner, value in mapping.value:
            lines[(section, prefix + str(inner.value))] = inner.start_mark.line + 1
            if isinstance(value, yaml.MappingNode):
                index(section, value, f"{prefix}{inner.value}.")

    if isinstance(node, yaml.MappingNode):
        for key, value in node.value:
            lines[(str(key.value), None)] = key.start_mark.line + 1
            if isinstance(value, yaml.MappingNode):
                index(str(key.value), value, "")
    return data, lines


def _preset_layers(ref: str, chain: tuple[str, ...] = ()) -> list[tuple[dict[str, Any], Where]]:
    """A preset and its ``base:`` chain as layers, the base first; each layer knows where its entries are.

    ``ref`` is a packaged preset's name or a path to a YAML file; a file's ``base:`` may name a packaged
    preset or another file (relative to the first file's folder).
    """
    if ref in chain:
        raise ConfigError(f"preset {chain[0]}: its base chain loops ({' -> '.join((*chain, ref))})")
    if _is_preset_file(ref):
        path = Path(ref)
        if not path.is_file():
            raise ConfigError(f"preset file {ref} does not exist; give a path to a YAML file or a packaged preset "
                              f"({', '.join(available_presets())})")
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as err:
            raise ConfigError(f"preset file {ref} is not readable ({err})") from None
        data, lines = _yaml_with_lines(text, str(path))

        def where(section: str | None, key: str | None, path: Path = path, lines=lines) -> str:
            line = (lines.get((section, key)) or lines.get((section, None))) if section is not None else None
            return f"{path}:{line}: " if line else f"{path}: "
    else:
        presets = available_presets()
        if ref not in presets:
            raise ConfigError(f"unknown preset '{ref}'; valid presets: {', '.join(presets)} "
                              "(or a path to a YAML file)")
        plugin = plugin_presets().get(ref)
        source = plugin[0] if plugin else resources.files("drago") / "presets" / f"{ref}.yaml"
        try:
            data = yaml.safe_load(source.read_text(encoding="utf-8")) or {}
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
            raise ConfigError(f"preset {ref} ({source}) is not readable: {' '.join(str(err).split())}") from None
        package = f" of package {plugin[1]}" if plugin else ""

        def where(section: str | None, key: str | None, ref: str = ref, package: str = package) -> str:
            return f"preset {ref}{package}: "
    data = data or {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where(None, None)}a preset must be a mapping of sections (env, agent, train, ...)")
    base = data.pop("base", None)
    if base is None:
        return [(data, where)]
    base = str(base)
    if _is_preset_file(ref) and _is_preset_file(base) and not Path(base).is_absolute():
        base = str(Path(ref).parent / base)
    return [*_preset_layers(base, (*chain, ref)), (data, where)]


#: The preset whose own settings (not its base's) shrink any preset to a run of seconds (``smoke=True``).
SMOKE_PRESET = "smoke"


# ---- the tree of settings ---------------------------------------------------------------------------
def _subsection(section: Any, name: str) -> bool:
    return isinstance(getattr(section, name, None), _Section)


def _leaves(section: Any, prefix: str) -> list[tuple[str, Any, dataclasses.Field]]:
    """``(key, owning section, field)`` of every setting in ``section`` and its subsections, in field order."""
    out = []
    for f in fields(section):
        if _subsection(section, f.name):
            out += _leaves(getattr(section, f.name), f"{prefix}.{f.name}")
        else:
            out.append((f"{prefix}.{f.name}", section, f))
    return out


def setting_fields(cfg: Config | None = None) -> list[tuple[str, Any, dataclasses.Field]]:
    """``(key, owning section, field)`` of every setting of ``cfg`` (default: the defaults), e.g.
    ``("agent.tdmpc.horizon", cfg.agent.tdmpc, Field(horizon))``."""
    cfg = cfg or Config()
    return [leaf for name in SECTIONS for leaf in _leaves(getattr(cfg, name), name)]


def _types(cls: type) -> dict[str, Any]:
    """A section's declared field types, resolved by :func:`typing.get_type_hints` (once per class)."""
    hints = _TYPES.get(cls)
    if hints is None:
        hints = _TYPES[cls] = typing.get_type_hints(cls)
    return hints


_TYPES: dict[type, dict[str, Any]] = {}


def _section_at(cfg: Config, path: str) -> Any:
    target: Any = cfg
    for part in path.split("."):
        target = getattr(target, part)
    return target


# ---- renamed settings -------------------------------------------------------------------------------
def _renamed() -> dict[str, tuple[str, ...]]:
    """Old key -> its new key(s): the agent kinds' and the methods' settings moved into sections of their own
    (docs: Changelog). CEM momentum was one setting for both agent kinds and is now one in each."""
    out: dict[str, tuple[str, ...]] = {f"agent.{f.name}": (f"agent.tdmpc.{f.name}",) for f in fields(TdmpcConfig)}
    out["agent.momentum"] = ("agent.tdmpc.momentum", "agent.pets.momentum")
    out.update({f"agent.pets_{f.name}": (f"agent.pets.{f.name}",) for f in fields(PetsAgentConfig)
                if f.name != "momentum"})
    out.update({f"method.vae_{f.name}": (f"method.vae.{f.name}",) for f in fields(VaeConfig)})
    out.update({f"method.rehearsal_{f.name}": (f"method.rehearsal.{f.name}",) for f in fields(RehearsalConfig)
                if f.name != "weight"})
    out["method.rehearsal_lambda"] = ("method.rehearsal.weight",)
    out.update({f"method.{f.name}": (f"method.reviewer.{f.name}",) for f in fields(ReviewerConfig)})
    for section in ("ewc", "replay", "curiosity"):
        out.update({f"method.{section}_{f.name}": (f"method.{section}.{f.name}",)
                    for f in fields(SECTION_CLASSES[f"method.{section}"])})
    return out


#: Settings renamed when the agent kinds and the methods got sections of their own: old key -> new key(s).
#: A run's saved config.yaml, a checkpoint's config and a record's protocol are migrated silently; a preset or an
#: override that names an old key is refused with the new name.
RENAMED: dict[str, tuple[str, ...]] = _renamed()
_RENAMED_SHORT = {old.partition(".")[2]: new for old, new in RENAMED.items()}


def _renamed_message(key: str, value: str | None = None) -> str | None:
    new = RENAMED.get(key) or (_RENAMED_SHORT.get(key) if "." not in key else None)
    if new is None:
        return None
    write = " and ".join(f"{n}={value}" if value is not None else n for n in new)
    return f"setting '{key}' was renamed; write {write}"


def migrate_saved(data: dict[str, Any]) -> dict[str, Any]:
    """A saved config (a run's ``config.yaml``, a checkpoint's config) with renamed keys moved to their new
    place; anything else unchanged (a copy, never the argument)."""
    import copy

    data = copy.deepcopy(data)
    for old, new_keys in RENAMED.items():
        section, _, name = old.partition(".")
        values = data.get(section)
        if not (isinstance(values, dict) and name in values):
            continue
        value = values.pop(name)
        for new in new_keys:
            *path, leaf = new.split(".")
            target = data
            for part in path:
                target = target.setdefault(part, {})
            target.setdefault(leaf, value)
    return data


def migrate_flat(settings: dict[str, Any]) -> dict[str, Any]:
    """``{"section.key": value}`` settings (a record's protocol) with renamed keys under their new names."""
    out: dict[str, Any] = {}
    for key, value in settings.items():
        for new in RENAMED.get(key, (key,)):
            out.setdefault(new, value)
    return out


# ---- which settings a run reads ---------------------------------------------------------------------
#: The method sections (``vae``, ``ewc``, ...) each registered method reads, by method name. The continual
#: layer, which the config sits below, installs it from its registry (``ContinualMethod.reads``).
methods_reads: Callable[[], dict[str, tuple[str, ...]]] = dict


def applies(key: str, kind: str, method: str) -> bool:
    """Whether a run of agent ``kind`` and method ``method`` reads the setting ``key``: an agent kind's
    section (``agent.pets.*``) only under that kind, a method's section (``method.ewc.*``) only for methods
    that declare it; every other setting always. A method unknown here reads every section."""
    parts = key.split(".")
    if len(parts) < 3:
        return True
    if parts[0] == "agent":
        return parts[1] == kind
    if parts[0] == "method":
        reads = methods_reads().get(method)
        return reads is None or parts[1] in reads
    return True


def inapplicable_settings(cfg: Config) -> tuple[str, ...]:
    """Every setting of ``cfg`` its agent kind and method do not read (left out of a record's protocol)."""
    return tuple(key for key, _, _ in setting_fields(cfg) if not applies(key, cfg.agent.kind, cfg.method.name))


def _readers(key: str) -> str:
    """Who reads a section's setting, for messages: ``agent.kind=pets`` or ``methods drago, ewc``."""
    parts = key.split(".")
    if parts[0] == "agent":
        return f"agent.kind={parts[1]}"
    load_method_plugins()
    from_methods = [name for name, reads in methods_reads().items() if parts[1] in reads]
    return ("method " if len(from_methods) == 1 else "methods ") + ", ".join(from_methods)


def refuse_inapplicable(cfg: Config, keys: list[str]) -> None:
    """Raise for the first of ``keys`` (settings someone set by name) that ``cfg``'s agent kind or method
    would ignore, naming who reads it."""
    for key in keys:
        if not applies(key, cfg.agent.kind, cfg.method.name):
            raise ConfigError(f"setting '{key}' applies to {_readers(key)}, and this run is agent.kind="
                              f"{cfg.agent.kind}, method {cfg.method.name}: remove it")


def overrides_for(overrides: list[str] | tuple[str, ...], kind: str, method: str) -> list[str]:
    """The ``key=value`` overrides that a run of agent ``kind`` and method ``method`` reads: a study passes each
    of its runs these, from one list for all its methods (a plug-in method's own setting is kept: its method
    checks it)."""
    kept = []
    for item in overrides:
        key, _, raw = item.partition("=")
        full = apply_override(Config(), key.strip(), raw.strip(), pending=[])
        if full is None or applies(full, kind, method):
            kept.append(item)
    return kept


def unread_overrides(overrides: list[str] | tuple[str, ...], kind: str,
                     methods: list[str] | tuple[str, ...]) -> str | None:
    """One line naming the first override that none of ``methods`` reads (with agent ``kind``), or None."""
    for item in overrides:
        if not any(item in overrides_for([item], kind, method) for method in methods):
            key = item.partition("=")[0].strip()
            full = apply_override(Config(), key, item.partition("=")[2].strip(), pending=[]) or key
            return f"setting '{full}' applies to {_readers(full)}, and none of this study's runs reads it: remove it"
    return None


# ---- building a config ------------------------------------------------------------------------------
def load_config(preset: str, overrides: list[str] | None = None, method: str | None = None,
                seed: int | None = None, smoke: bool = False, inapplicable_ok: bool = False) -> Config:
    """Build a validated config from a preset plus ``key=value`` overrides.

    Args:
        preset: a packaged preset's name (see :func:`available_presets`) or the path of a YAML file of the
            same form, whose ``base:`` may name a packaged preset.
        overrides: strings ``section.key=value`` or ``key=value`` for a key name that is unique
            across sections (``mlp_dim=128``).
        method: shortcut for ``method.name=...``.
        seed: shortcut for ``train.seed=...``.
        smoke: the preset's smoke path: the ``smoke`` preset's own settings (budgets, network and planner
            sizes) over the preset's, before the overrides; its domain, tasks, agent kind and method stay.
            The config's preset reads ``PRESET+smoke``.
        inapplicable_ok: accept overrides of settings the chosen agent kind or method does not read (a
            study's overrides, which apply to some of its methods); by default they are an error. A preset
            may always set them: one preset serves every method and agent kind.

    Raises:
        ConfigError: one line naming the bad preset, key or value.
    """
    if isinstance(overrides, str):
        raise ConfigError(f"overrides must be a list of 'key=value' strings, e.g. overrides=[{overrides!r}], "
                          f"not the string {overrides!r}")
    cfg = Config(preset=Path(preset).stem if _is_preset_file(preset) else preset)
    # A method.* key that is no built-in setting may be one the chosen method declares: kept until the method
    # is known (an override or --method can still change it), then resolved against its declaration.
    pending: list[tuple[str, Any, str, bool]] = []
    layers = _preset_layers(preset)
    if smoke:
        layers.append(_preset_layers(SMOKE_PRESET)[-1])
        cfg.preset = f"{cfg.preset}+smoke"
    for data, where in layers:
        _merge(cfg, data, where, pending)
    named: list[str] = []
    for item in overrides or []:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"override '{item}' is not of the form key=value")
        named.append(apply_override(cfg, key.strip(), raw.strip(), pending))
    if method is not None:
        cfg.method.name = method
    if seed is not None:
        cfg.train.seed = seed
    _resolve_method_options(cfg, pending)
    validate(cfg)
    if not inapplicable_ok:
        refuse_inapplicable(cfg, [key for key in named if key])
    return cfg


def _resolve_method_options(cfg: Config, pending: list[tuple[str, Any, str, bool]]) -> None:
    """Set each pending ``method.NAME`` the chosen method declares into ``cfg.method.options``."""
    if not pending:
        return
    load_method_plugins()
    declared = METHOD_SETTINGS.get(cfg.method.name, {})
    for name, value, prefix, from_text in pending:
        key = f"method.{name}"
        if name not in declared:
            candidates = [f"method.{n}" for n in declared] + [k for k, _, _ in setting_fields()
                                                              if k.startswith("method.")]
            own = (f"method '{cfg.method.name}' declares {', '.join(f'method.{n}' for n in declared)}; "
                   if declared else "")
            raise ConfigError(f"{prefix}{_unknown(key, candidates, own)}")
        kind = declared[name].kind
        cfg.method.options[name] = _parse(value, kind, key) if from_text else _coerce(value, kind, key)


def apply_override(cfg: Config, key: str, raw: str, pending: list | None = None) -> str | None:
    """Set one setting from its string form, converting to the field's declared type, and return its full
    key. With ``pending``, an unknown ``method.NAME`` is kept there for the chosen method's own settings
    (:func:`load_config`; None is returned for it)."""
    leaves = {k: (owner, f) for k, owner, f in setting_fields(cfg)}
    if "." not in key:
        owners = [k for k in leaves if k.rpartition(".")[2] == key]
        if not owners:
            raise ConfigError(_renamed_message(key, raw)
                              or f"unknown setting '{key}'; run `drago list --settings` for the valid keys")
        if len(owners) > 1:
            raise ConfigError(f"setting '{key}' is ambiguous; write one of: " + ", ".join(owners))
        key = owners[0]
    section = key.partition(".")[0]
    if section not in SECTIONS:
        raise ConfigError(f"unknown section '{section}' in '{key}'; valid sections: {', '.join(SECTIONS)}")
    if key in RENAMED:
        raise ConfigError(_renamed_message(key, raw))
    if key not in leaves:
        if key in SECTION_CLASSES:
            raise ConfigError(f"'{key}' is a section, not a setting; set one of its keys, e.g. "
                              f"{next(k for k in leaves if k.startswith(key + '.'))}=...")
        if section == "method" and key.count(".") == 1 and pending is not None:
            pending.append((key.partition(".")[2], raw, "", True))
            return None
        raise ConfigError(_unknown(key, list(leaves)))
    owner, f = leaves[key]
    setattr(owner, f.name, _parse(raw, _types(type(owner))[f.name], key))
    return key


def _merge(cfg: Config, data: dict[str, Any], where: Where | str, pending: list | None = None) -> None:
    """Set every ``section: {key: value}`` of ``data`` (subsections nested the same way); errors start with
    ``where(section, key)``. With ``pending``, an unknown method setting is kept there (:func:`load_config`)."""
    prefix = where if callable(where) else (lambda section, key, text=where: text)
    for section, values in data.items():
        if section == "preset":
            cfg.preset = str(values)
            continue
        if section not in SECTIONS:
            raise ConfigError(f"{prefix(section, None)}unknown section '{section}'; valid sections: {', '.join(SECTIONS)}")
        _merge_section(getattr(cfg, section), section, values, lambda key, s=section: prefix(s, key), pending)


def _merge_section(target: Any, path: str, values: Any, prefix: Callable[[str | None], str],
                   pending: list | None) -> None:
    if not isinstance(values, dict):
        raise ConfigError(f"{prefix(None)}section '{path}' must be a mapping of settings")
    declared = {f.name: f for f in fields(target)}
    for name, value in values.items():
        key = f"{path}.{name}"
        first = key.partition(".")[2]  # the key's path inside its section: the line a preset's message points at
        if name in declared and _subsection(target, name):
            _merge_section(getattr(target, name), key, value, prefix, pending)
            continue
        if name not in declared and path == "method" and pending is not None and key not in RENAMED:
            pending.append((name, value, prefix(first), False))
            continue
        if name not in declared:
            renamed = _renamed_message(key)
            if renamed:
                raise ConfigError(f"{prefix(first)}{renamed}")
            raise ConfigError(f"{prefix(first)}unknown setting '{key}'; valid keys in {path}: " + ", ".join(declared))
        try:
            setattr(target, name, _coerce(value, _types(type(target))[name], key))
        except ConfigError as err:
            raise ConfigError(f"{prefix(first)}{err}") from None


def _parse(raw: str, annotation: Any, key: str) -> Any:
    """Parse a command-line string with YAML rules, then check it against the declared type."""
    return _coerce(_parse_scalar(raw) if raw != "" else "", annotation, key)


def _parse_scalar(raw: str) -> Any:
    try:
        return yaml.safe_load(raw)
    except yaml.YAMLError:
        return raw


# YAML 1.1 reads an exponent without a dot ("3e-4", "1E5") as a string; that is how people write rates.
_EXPONENT_NUMBER = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")


def setting_value(value: Any, kind: Any, key: str) -> Any:
    """``value`` as a setting of type ``kind`` (a preset's YAML value, or one set in Python), named ``key`` in
    the one-line :class:`ConfigError` it raises when it is not one."""
    return _coerce(value, kind, key)


def _coerce(value: Any, kind: Any, key: str) -> Any:
    origin = typing.get_origin(kind)
    args = typing.get_args(kind)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        if isinstance(value, str) and value.lower() in ("none", "null") and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(value, inner[0], key)
    if origin is tuple:
        if isinstance(value, str):
            value = [_parse_scalar(v.strip()) for v in value.strip("()[]").split(",") if v.strip()]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"setting '{key}' expects a list, got {value!r}")
        return tuple(_coerce(v, args[0], key) for v in value)
    if kind is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"setting '{key}' expects true or false, got {value!r}")
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or int(value) != value:
            raise ConfigError(f"setting '{key}' expects an integer, got {value!r}")
        return int(value)
    if kind is float:
        if isinstance(value, str) and _EXPONENT_NUMBER.fullmatch(value.strip()):
            value = float(value)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"setting '{key}' expects a number, got {value!r}")
        return float(value)
    if kind is str:
        if isinstance(value, bool) and key in BOOLEAN_WORDS:
            return BOOLEAN_WORDS[key][value]
        if isinstance(value, (dict, list)):
            raise ConfigError(f"setting '{key}' expects a string, got {value!r}")
        return str(value)
    return value


# ---- validation -------------------------------------------------------------------------------------
# Range rules as data: each key once, each rule with one message.
POSITIVE = (
    "env.episode_length", "env.action_repeat", "agent.lr", "agent.batch_size",
    "agent.tdmpc.mlp_dim", "agent.tdmpc.horizon", "agent.tdmpc.iterations", "agent.tdmpc.num_samples",
    "agent.tdmpc.num_elites", "agent.tdmpc.update_freq", "agent.tdmpc.horizon_schedule_steps",
    "agent.tdmpc.std_schedule_steps", "agent.tdmpc.lr_schedule_steps", "agent.pets.members", "agent.pets.hidden",
    "agent.pets.layers", "agent.pets.particles", "agent.pets.horizon", "agent.pets.iterations",
    "agent.pets.population", "agent.pets.elites", "train.steps_per_task", "train.eval_freq",
    "train.eval_episodes", "train.checkpoint_freq", "method.vae.hidden_dim", "method.vae.latent_dim",
    "method.rehearsal.freq", "method.rehearsal.batch", "method.ewc.fisher_batches", "method.replay.capacity",
    "transfer.few_shot_episodes",
)
POSITIVE_OR_UNSET = ("train.learner_steps_per_task", "train.reviewer_steps_per_task", "train.eval_every_episodes",
                     "transfer.after")
NON_NEGATIVE = (
    "agent.seed_steps", "train.threads", "train.heldout_episodes", "transfer.pre_rollout_steps",
    "method.vae.recon_coef", "method.vae.kl_coef", "method.rehearsal.weight", "method.reviewer.cost_coef",
    "method.ewc.coef", "method.curiosity.coef",
)
NON_NEGATIVE_OR_UNSET = ("train.updates_per_episode",)
UNIT_INTERVAL = ("agent.tdmpc.discount", "agent.tdmpc.rho", "agent.tdmpc.tau", "agent.tdmpc.momentum",
                 "agent.tdmpc.mixture_coef", "agent.pets.momentum", "method.reviewer.threshold_momentum")
CHOICES: dict[str, tuple[str, ...]] = {
    "agent.kind": AGENT_KINDS,
    "agent.schedule_clock": ("task", "learner"),
    "agent.tdmpc.elite_selection": ELITE_SELECTIONS,
    "agent.tdmpc.precision": PRECISIONS,
    "agent.tdmpc.compile": COMPILE_CHOICES,
    "agent.pets.propagation": ("tsinf", "ts1"),
    "agent.pets.reward": ("learned", "known"),
    "method.vae.data": ("combined", "learner"),
    "method.rehearsal.mode": ("separate", "joint"),
    "method.rehearsal.target": ("pre_squash", "post_squash"),
    "method.reviewer.intrinsic_reward": INTRINSIC_REWARDS,
    "transfer.pre_rollout_planning": PRE_ROLLOUT_PLANNING,
    "train.wandb": ("off", "online", "offline"),
}
#: Choice settings where YAML reads a word as a boolean (off, no, false: False; on, yes, true: True): the choice
#: each boolean stands for.
BOOLEAN_WORDS: dict[str, tuple[str, str]] = {"train.wandb": ("off", "online"),
                                             "agent.tdmpc.compile": ("false", "true")}


def _get(cfg: Config, key: str) -> Any:
    path, _, name = key.rpartition(".")
    return getattr(_section_at(cfg, path), name)


def _check_ranges(cfg: Config) -> None:
    for key in POSITIVE + POSITIVE_OR_UNSET:
        value = _get(cfg, key)
        if value is not None and value <= 0:
            raise ConfigError(f"setting '{key}' must be positive, got {value}")
    for key in NON_NEGATIVE + NON_NEGATIVE_OR_UNSET:
        value = _get(cfg, key)
        if value is not None and value < 0:
            raise ConfigError(f"setting '{key}' must be >= 0, got {value}")
    for key in UNIT_INTERVAL:
        value = _get(cfg, key)
        if not 0.0 <= value <= 1.0:
            raise ConfigError(f"setting '{key}' must lie in [0, 1], got {value}")
    if cfg.agent.kind not in CHOICES["agent.kind"]:
        load_agent_plugins()
    for key, valid in CHOICES.items():
        if _get(cfg, key) not in valid:
            raise ConfigError(f"unknown {key} '{_get(cfg, key)}'; valid choices: {', '.join(valid)}")


def _check_domain_and_tasks(cfg: Config) -> None:
    env = cfg.env
    if not is_domain(env.domain):
        raise ConfigError(f"unknown domain '{env.domain}'; valid domains: {', '.join(available_domains())}, "
                          "or dmc:DOMAIN for a stock DeepMind Control domain")
    domain = get_domain(env.domain)
    if domain.tabular and env.action_repeat != 1:  # one agent step must stay one transition of the table
        raise ConfigError(f"setting 'env.action_repeat' must be 1 for the grid and other tabular domains "
                          f"({env.domain}), got {env.action_repeat}")
    if not domain.dense_reward and env.dense_reward is not None:
        raise ConfigError(f"setting 'env.dense_reward' applies to the grid only; leave it unset for {env.domain}")
    if not domain.dense_reward and cfg.transfer.reward is not None:
        raise ConfigError(f"setting 'transfer.reward' applies to the grid only; leave it unset for {env.domain}")
    for module in domain.requires:
        if importlib.util.find_spec(module) is None:
            raise ConfigError(f"domain {env.domain} needs {module}, which is not installed: "
                              "pip install -e '.[dmc]' (scripts/setup.sh installs it)")
    if not env.tasks:
        raise ConfigError("env.tasks is empty; name at least one task")
    valid_tasks = available_tasks(env.domain)
    for task in env.tasks:
        if task not in valid_tasks:
            raise ConfigError(f"unknown task '{task}' for domain {env.domain}; valid tasks: " + ", ".join(valid_tasks))
    if cfg.transfer.pre_rollout_checkpoint is not None and domain.tabular:
        # A tabular task's optimum and exact evaluations assume each episode starts at the task's start.
        raise ConfigError(f"setting 'transfer.pre_rollout_checkpoint' applies to DeepMind Control test tasks, "
                          f"not to the grid or other tabular domains ({env.domain})")


def _check_relations(cfg: Config) -> None:
    """Rules that tie two settings together."""
    agent, tdmpc, pets, train = cfg.agent, cfg.agent.tdmpc, cfg.agent.pets, cfg.train
    if tdmpc.lr_final is not None and not 0 < tdmpc.lr_final <= agent.lr:
        raise ConfigError(f"setting 'agent.tdmpc.lr_final' must lie in (0, agent.lr={agent.lr}], got "
                          f"{tdmpc.lr_final}; leave it unset (null) for a constant lr")
    if pets.elites > pets.population:
        raise ConfigError(f"agent.pets.elites ({pets.elites}) must not exceed agent.pets.population "
                          f"({pets.population})")
    if tdmpc.num_elites > tdmpc.num_samples:
        raise ConfigError(f"agent.tdmpc.num_elites ({tdmpc.num_elites}) must not exceed agent.tdmpc.num_samples "
                          f"({tdmpc.num_samples})")
    if applies("agent.pets.reward", agent.kind, cfg.method.name):
        if pets.reward == "known" and get_domain(cfg.env.domain).known_reward is None:
            raise ConfigError(f"agent.pets.reward=known needs a reward known as a function of observations, as the "
                              f"grid's (env.domain=minigrid); {cfg.env.domain} declares none: use "
                              "agent.pets.reward=learned")
    if applies("agent.tdmpc.horizon", agent.kind, cfg.method.name) and cfg.env.episode_length <= tdmpc.horizon:
        raise ConfigError(f"env.episode_length ({cfg.env.episode_length}) must exceed agent.tdmpc.horizon "
                          f"({tdmpc.horizon}) so that training sequences fit inside an episode")
    probs = agent.random_action_probs
    if probs and (min(probs) < 0 or abs(sum(probs) - 1.0) > 1e-6):
        raise ConfigError(f"agent.random_action_probs must be non-negative numbers summing to 1, got {probs}")
    rehearsal = cfg.method.rehearsal
    if applies("method.rehearsal.weight", agent.kind, cfg.method.name) and rehearsal.mode == "separate" \
            and rehearsal.weight != 1.0:
        # Separate mode is the official code's own optimizer step, which has no weight; a silent 1.0 would run
        # another experiment than the one asked for.
        raise ConfigError(f"setting 'method.rehearsal.weight' ({rehearsal.weight}) weights the rehearsal term only "
                          "with method.rehearsal.mode=joint; add method.rehearsal.mode=joint or leave the weight at "
                          "1.0")
    if not 0.0 <= cfg.method.replay.fraction < 1.0:
        # The old rows' weight is f / (1 - f): all-old batches would leave the current task unweighted.
        raise ConfigError(f"setting 'method.replay.fraction' must lie in [0, 1), got {cfg.method.replay.fraction}")
    if cfg.transfer.reward not in (None, "dense", "sparse"):
        raise ConfigError(f"unknown transfer.reward '{cfg.transfer.reward}'; valid choices: dense, sparse, "
                          "or leave it unset for each task's own")
    device = train.device
    if not (device == "cpu" or device == "cuda" or (device.startswith("cuda:") and device[5:].isdigit())):
        raise ConfigError(f"unknown device '{device}'; use cpu, cuda or cuda:N")


def _check_types(cfg: Config) -> None:
    """Every value of the declared type: a config built in Python (``cfg.train.steps_per_task = "abc"``) is held
    to what a preset or an override would have been converted to."""
    if not isinstance(cfg, Config):
        raise ConfigError(f"expected a drago Config (drago.load_config(...)), got {type(cfg).__name__}")
    for key, target, f in setting_fields(cfg):
        kind, value = _types(type(target))[f.name], getattr(target, f.name)
        if isinstance(value, str) and kind is not str and not (
                typing.get_origin(kind) in (typing.Union, types.UnionType) and str in typing.get_args(kind)):
            raise ConfigError(f"setting '{key}' expects {_type_words(kind)}, got the string {value!r}; "
                              "set it to a value of that type")
        # Normalised in place (a list where a tuple is declared, 100.0 for an integer): the same setting, and
        # the form a run's config.yaml and a record's protocol hold.
        object.__setattr__(target, f.name, _coerce(value, kind, key))


def _type_words(kind: Any) -> str:
    args = [a for a in typing.get_args(kind) if a is not type(None)] or [kind]
    words = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}
    return " or ".join(words.get(a, "a list" if typing.get_origin(a) is tuple else str(a)) for a in args)


def validate(cfg: Config) -> None:
    """Check types, ranges and names once, so nothing fails an hour into a run.

    The method's name is checked where methods are known (:func:`drago.continual.check_method`): settings
    sit below the methods that read them.
    """
    _check_types(cfg)
    _check_domain_and_tasks(cfg)
    _check_ranges(cfg)
    _check_relations(cfg)


def _to_plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _to_plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_to_plain(v) for v in value]
    return value


def describe_settings(plugins: bool = False) -> list[tuple[str, str, Any]]:
    """(key, type, default) for every setting, for `drago list --settings`; with ``plugins``, also the
    settings plug-in methods declare (type ``KIND, METHOD only``)."""
    rows = []
    for key, target, f in setting_fields():
        kind = _types(type(target))[f.name]
        rows.append((key, _type_name(kind), getattr(target, f.name)))
    if plugins:
        load_method_plugins()
        for method, declared in METHOD_SETTINGS.items():
            rows += [(f"method.{name}", f"{setting.kind.__name__}, {method} only", setting.default)
                     for name, setting in declared.items()]
    return rows


def _type_name(kind: Any) -> str:
    """A declared type as written in the source: ``int``, ``float | None``, ``tuple[str, ...]``."""
    return getattr(kind, "__name__", None) if typing.get_origin(kind) is None else str(kind).replace("typing.", "")
