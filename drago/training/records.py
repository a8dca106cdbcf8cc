"""Run records: a finished unit of a study as one small, versioned file meant to be committed.

A record holds everything the analysis of a run needs and nothing it does not (docs: Command line,
"Records: studies that outlive the machine"):

* ``protocol``: what decides the run's results (its settings, those of its transfer cases, and the
  evaluations made from its checkpoints) and their digest; not threads, paths, W&B or the commit, so the
  same unit run on another machine has the same protocol;
* ``provenance``: drago's version, the commit and whether the tree was dirty, torch and Python, the CPU,
  threads and device, and when it was recorded;
* ``files``: the run directory's text files (config, summary, logs, visitation, every evaluation made from
  the checkpoints) and those of its transfer runs under ``transfer/``, by relative path. Checkpoints,
  buffers, held-out sets and TensorBoard or W&B files are never recorded.

The file is gzip-compressed JSON (``.json.gz``, written with a fixed timestamp so the same record has the
same bytes) and written atomically. A reader refuses an unknown format or version with one line. A record
is read back as a *record view*: a run directory materialized from its files, without checkpoints, which
every reader of run directories accepts (the evaluations are then read from their files, never recomputed).
"""

from __future__ import annotations

import gzip
import hashlib
import json
import os
import platform
import subprocess
import sys
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from drago.config import Config, ConfigError, applies, inapplicable_settings, migrate_flat
from drago.training.rundir import (
    CHECKPOINT_FOLDER,
    CONFIG_FILE,
    HELDOUT_FOLDER,
    RESOLVED_AT_START,
    SETTINGS_THAT_MAY_DIFFER,
    TRANSFER_FOLDER,
    WANDB_RUN_FILE,
    RunDirError,
    atomic_write,
    atomic_write_text,
    flat_settings,
)

__all__ = ["RECORD_FORMAT", "RECORD_SUFFIX", "RECORD_VERSION", "RECORD_VIEW_FILE", "RecordError", "export_record",
           "find_records", "is_record_view", "materialize", "protocol_digest", "protocol_diffs", "read_record",
           "record_view_meta", "run_protocol", "write_record"]

RECORD_FORMAT = "drago-record"
#: 2: the agent kinds' and the methods' settings in sections of their own (``agent.tdmpc.horizon``), and a
#: protocol without the settings its agent kind and method do not read. Version 1 records are migrated on reading.
RECORD_VERSION = 2
RECORD_SUFFIX = ".json.gz"
#: Written into a record view: the record's protocol and provenance, and the mark that the view has no checkpoints.
RECORD_VIEW_FILE = "record.json"
#: What a record keeps of a run directory: its text files; folders of binary state are never walked.
RECORDED_SUFFIXES = (".csv", ".json", ".yaml", ".log")
UNRECORDED_FOLDERS = (CHECKPOINT_FOLDER, HELDOUT_FOLDER, "tb", "wandb")
UNRECORDED_FILES = (WANDB_RUN_FILE, RECORD_VIEW_FILE)
#: Settings that name files, not results: a transfer's checkpoint is the same stage wherever the run lies.
PATH_SETTINGS = ("transfer.checkpoint", "transfer.pre_rollout_checkpoint")
#: Left out of a protocol: where and how a run logs, and what it resolved for its machine (``auto`` precision
#: and compilation, which the record's provenance keeps), so that a study continues on another machine.
NOT_PROTOCOL = (*SETTINGS_THAT_MAY_DIFFER, *PATH_SETTINGS, *RESOLVED_AT_START, "train.tensorboard")
#: Settings left out of a protocol while they hold this value: a plug-in method's own settings (none for the
#: built-in methods), and settings added after records existed whose default reproduces those records.
NEUTRAL: dict[str, Any] = {"method.options": {}, "agent.schedule_clock": "task"}


class RecordError(RunDirError):
    """A record that cannot be read or written as asked; the message is one line."""


# ---- protocol --------------------------------------------------------------------------------------
def _protocol_settings(cfg: Config) -> dict[str, Any]:
    idle = idle_settings(cfg)
    settings = {key: value for key, value in flat_settings(cfg).items() if key not in NOT_PROTOCOL and key not in idle}
    # Settings that were added after records existed and whose default changes nothing are left out at that
    # default, so the records made before them keep their protocol.
    return {key: value for key, value in settings.items() if NEUTRAL.get(key, object()) != value}


def idle_settings(cfg: Config) -> frozenset[str]:
    """The settings of ``cfg`` that its run does not read or that cannot change its results: not part of its
    protocol, and two runs of a method that differ only in them are runs of one variant (the report's groups)."""
    return frozenset((*settings_without_effect(cfg), *inapplicable_settings(cfg)))


def settings_without_effect(cfg: Config) -> tuple[str, ...]:
    """Settings that cannot change the results of ``cfg``'s method: left out of its protocol, and a run
    directory that differs from a study's only in them is the study's run."""
    from drago.continual import get_method

    try:
        second_agent = bool(get_method(cfg.method.name).second_agent)
    except ConfigError:  # a plug-in method not installed here: every setting may matter
        second_agent = True
    # Without a second agent a task's steps are its learner's: both clocks count the same.
    return () if second_agent else ("agent.schedule_clock",)


def run_protocol(run: Config, transfers: Mapping[str, Config], evaluations: Sequence[str]) -> dict[str, Any]:
    """What decides a unit's results: the run's settings, each transfer case's (by its directory name) and
    the names of the evaluations made from the checkpoints (a new evaluation is a new protocol)."""
    return {"run": _protocol_settings(run),
            "transfers": {name: _protocol_settings(cfg) for name, cfg in sorted(transfers.items())},
            "evaluations": sorted(evaluations)}


def _migrate_v1_settings(settings: Mapping[str, Any]) -> dict[str, Any]:
    """A version-1 protocol's settings as this version's: renamed keys under their new names, and without the
    settings that the run's agent kind and method do not read (what :func:`_protocol_settings` leaves out)."""
    settings = migrate_flat(dict(settings))
    kind, method = settings.get("agent.kind", "tdmpc"), settings.get("method.name", "continual")
    return {key: value for key, value in settings.items() if applies(key, kind, method)}


def _migrate_v1(record: dict[str, Any]) -> dict[str, Any]:
    protocol = record["protocol"]
    migrated = {"run": _migrate_v1_settings(protocol.get("run") or {}),
                "transfers": {name: _migrate_v1_settings(settings)
                              for name, settings in (protocol.get("transfers") or {}).items()},
                "evaluations": protocol.get("evaluations") or []}
    resolved = record.get("provenance", {}).get("resolved")
    if isinstance(resolved, dict):
        record["provenance"]["resolved"] = migrate_flat(resolved)
    record["protocol"] = {"digest": protocol_digest(migrated), **migrated}
    record["version"] = RECORD_VERSION
    return record


def protocol_digest(protocol: Mapping[str, Any]) -> str:
    """A short, stable digest of a protocol (sha256 of its canonical JSON)."""
    text = json.dumps(protocol, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


def protocol_diffs(recorded: Mapping[str, Any], wanted: Mapping[str, Any], most: int = 3) -> str:
    """``key: there, here`` for the first ``most`` settings in which two protocols differ, as one phrase."""
    def flat(protocol: Mapping[str, Any]) -> dict[str, Any]:
        out = {f"run {k}": v for k, v in (protocol.get("run") or {}).items()}
        for name, settings in (protocol.get("transfers") or {}).items():
            out.update({f"{name} {k}": v for k, v in settings.items()})
        out["evaluations"] = protocol.get("evaluations")
        return out

    there, here = flat(recorded), flat(wanted)
    diffs = [f"{key}: {there.get(key, 'absent')!r} recorded, {here.get(key, 'absent')!r} now"
             for key in dict.fromkeys([*here, *there]) if there.get(key, "absent") != here.get(key, "absent")]
    more = f" and {len(diffs) - most} more" if len(diffs) > most else ""
    return "; ".join(diffs[:most]) + more


# ---- provenance ------------------------------------------------------------------------------------
def _git(args: Sequence[str], cwd: Path) -> str | None:
    try:
        return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, check=True,
                              timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None


def cpu_model() -> str:
    """The CPU's model name (Linux ``/proc/cpuinfo``; elsewhere what the platform says)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.partition(":")[2].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("drago")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown"


def provenance(cfg: Config) -> dict[str, Any]:
    """Who made a record, where and with what: enough to tell two records' machines and code apart."""
    import torch

    source = Path(__file__).resolve().parents[2]  # the checkout (or site-packages) holding drago
    commit = _git(["rev-parse", "HEAD"], source)
    dirty = None if commit is None else bool(_git(["status", "--porcelain", "--untracked-files=no"], source))
    return {"drago": _version(), "commit": commit, "dirty": dirty,
            "torch": torch.__version__, "python": platform.python_version(), "platform": sys.platform,
            "cpu": cpu_model(), "cores": os.cpu_count(), "threads": cfg.train.threads, "device": cfg.train.device,
            "resolved": {key: value for key, value in flat_settings(cfg).items() if key in RESOLVED_AT_START},
            "recorded": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")}


# ---- writing and reading ---------------------------------------------------------------------------
def _recorded_files(run_dir: Path) -> dict[str, str]:
    files: dict[str, str] = {}
    for folder, subfolders, names in os.walk(run_dir):
        subfolders[:] = sorted(s for s in subfolders if s not in UNRECORDED_FOLDERS)
        for name in sorted(names):
            if name.startswith(".") or name in UNRECORDED_FILES or not name.endswith(RECORDED_SUFFIXES):
                continue
            path = Path(folder) / name
            try:
                files[path.relative_to(run_dir).as_posix()] = path.read_text(encoding="utf-8")
            except (OSError, UnicodeDecodeError) as err:
                raise RecordError(f"cannot record {path} ({err})") from None
    return files


def export_record(run_dir: str | Path, protocol: Mapping[str, Any], cfg: Config) -> dict[str, Any]:
    """The record of a run directory (not yet written): its protocol, provenance and text files.

    Raises:
        RecordError: no ``config.yaml`` in ``run_dir``, or a file that cannot be read.
    """
    run_dir = Path(run_dir)
    if not (run_dir / CONFIG_FILE).is_file():
        raise RecordError(f"{run_dir} is not a drago run directory (no {CONFIG_FILE}); nothing to record")
    return {"format": RECORD_FORMAT, "version": RECORD_VERSION,
            "unit": {"preset": cfg.preset, "method": cfg.method.name, "seed": int(cfg.train.seed)},
            "protocol": {"digest": protocol_digest(protocol), **protocol},
            "provenance": provenance(cfg), "files": _recorded_files(run_dir)}


def write_record(record: Mapping[str, Any], path: str | Path) -> Path:
    """Write a record atomically as gzip-compressed JSON with a fixed timestamp (same record, same bytes)."""
    data = json.dumps(record, indent=None, separators=(",", ":"), sort_keys=False).encode("utf-8")

    def write(handle: Any) -> None:
        with gzip.GzipFile(fileobj=handle, mode="wb", compresslevel=9, mtime=0, filename="") as packed:
            packed.write(data)

    return atomic_write(path, write, durable=True)


def read_record(path: str | Path) -> dict[str, Any]:
    """A record's contents, checked.

    Raises:
        RecordError: a missing, corrupt or truncated file, another format, or a version this drago does not
            know (one line naming the file and what to do).
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
        data = json.loads(gzip.decompress(raw).decode("utf-8"))
    except FileNotFoundError:
        raise RecordError(f"record {path} does not exist") from None
    except (OSError, EOFError, UnicodeDecodeError, json.JSONDecodeError, gzip.BadGzipFile) as err:
        why = str(err).splitlines()[0] if str(err) else "truncated"
        raise RecordError(f"record {path} is corrupt ({type(err).__name__}: {why}); delete it so that its unit "
                          "runs again, or restore it from the repository") from None
    if not isinstance(data, dict) or data.get("format") != RECORD_FORMAT:
        raise RecordError(f"{path} is not a drago run record (no format '{RECORD_FORMAT}')")
    version = data.get("version")
    if version == 1 and isinstance(data.get("protocol"), dict):
        data = _migrate_v1(data)
        version = RECORD_VERSION
    if version != RECORD_VERSION:
        raise RecordError(f"record {path} has format version {version!r}; this drago reads version {RECORD_VERSION}: "
                          "use the drago release that wrote it")
    files, protocol = data.get("files"), data.get("protocol")
    if not (isinstance(files, dict) and CONFIG_FILE in files and isinstance(protocol, dict)
            and isinstance(protocol.get("digest"), str)):
        raise RecordError(f"record {path} lacks its files, config or protocol digest; it cannot be used")
    return data


def find_records(folder: str | Path) -> list[Path]:
    """The record files in ``folder`` and below it, sorted by path."""
    folder = Path(folder)
    if folder.is_file():
        return [folder] if folder.name.endswith(RECORD_SUFFIX) else []
    return sorted(p for p in folder.rglob(f"*{RECORD_SUFFIX}") if p.is_file() and not p.name.startswith("."))


def materialize(record: Mapping[str, Any], into: str | Path) -> Path:
    """Write a record's files into the folder ``into`` (a *record view*, created afresh) and return it."""
    into = Path(into)
    into.mkdir(parents=True, exist_ok=True)
    for relative, text in record["files"].items():
        target = (into / relative).resolve()
        if into.resolve() not in target.parents:  # a hand-edited record must not write outside its view
            raise RecordError(f"a record names the file '{relative}', outside its run directory; it cannot be used")
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(text, encoding="utf-8")
    meta = {key: record[key] for key in ("unit", "protocol", "provenance") if key in record}
    atomic_write_text(into / RECORD_VIEW_FILE, json.dumps(meta, indent=1) + "\n")
    for transfer in (into / TRANSFER_FOLDER).glob(f"*/{CONFIG_FILE}"):
        atomic_write_text(transfer.parent / RECORD_VIEW_FILE, json.dumps(meta, indent=1) + "\n")
    return into


def is_record_view(run_dir: str | Path) -> bool:
    """True for a run directory materialized from a record: it has no checkpoints, its evaluations are files."""
    return (Path(run_dir) / RECORD_VIEW_FILE).is_file()


def record_view_meta(run_dir: str | Path) -> dict[str, Any]:
    """The protocol and provenance of a record view (empty for an unreadable file)."""
    try:
        data = json.loads((Path(run_dir) / RECORD_VIEW_FILE).read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    return data if isinstance(data, dict) else {}
