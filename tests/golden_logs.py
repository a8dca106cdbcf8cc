"""The golden logs: short runs of every method with both agent kinds, whose logs a change that moves code
must leave byte-identical (docs: Design, "Changing code without changing results").

    .venv/bin/python tests/golden_logs.py          # record the digests of this machine's kind of CPU

Records are per torch version and CPU capability (AVX2, AVX512, ...): the same seed on the same kind of CPU
gives the same bits, another kind may round differently. Record them before a change, never to make a
failing comparison pass.
"""

from __future__ import annotations

import hashlib
import json
import sys
import tempfile
from pathlib import Path

GOLDEN = Path(__file__).resolve().parent / "golden" / "logs.json"
LOGS = ("train.csv", "eval.csv")
TINY = ["train.steps_per_task=200", "agent.seed_steps=100", "train.checkpoint_freq=100", "train.tensorboard=false",
        "agent.tdmpc.mlp_dim=16", "agent.batch_size=16", "agent.tdmpc.iterations=1", "agent.tdmpc.num_samples=8",
        "agent.tdmpc.num_elites=2",
        "train.threads=1", "env.tasks=[room1,room2]", "method.rehearsal.batch=16", "method.ewc.fisher_batches=2",
        "method.replay.capacity=50"]
PETS = ["agent.kind=pets", "agent.pets.members=2", "agent.pets.hidden=16", "agent.pets.layers=2",
        "agent.pets.particles=2", "agent.pets.horizon=3", "agent.pets.iterations=1", "agent.pets.population=8",
        "agent.pets.elites=2", "train.updates_per_episode=5"]


def machine_key() -> str:
    import torch

    return f"torch {torch.__version__}, {torch.backends.cpu.get_cpu_capability()}"


def cases() -> list[tuple[str, str]]:
    """(agent kind, method) of every method each agent kind runs."""
    from drago.config import ConfigError, load_config
    from drago.continual import available_methods, check_method

    out = []
    for kind, extra in (("tdmpc", []), ("pets", PETS)):
        for method in available_methods():
            try:
                check_method(load_config("smoke", [*TINY, *extra], method=method, inapplicable_ok=True))
            except ConfigError:
                continue  # a method this agent cannot run (curiosity needs TD-MPC's value heads)
            out.append((kind, method))
    return out


def digests(kind: str, method: str, folder: Path) -> dict[str, str]:
    """Train the case into ``folder`` and return the sha256 of each log."""
    import drago

    # One list of overrides for every case, as a study's: each case reads the settings of its kind and method.
    cfg = drago.load_config("smoke", [*TINY, *(PETS if kind == "pets" else [])], method=method, seed=3,
                            inapplicable_ok=True)
    drago.train(cfg, out=folder / f"{kind}-{method}", progress=False)
    return {name: hashlib.sha256((folder / f"{kind}-{method}" / name).read_bytes()).hexdigest() for name in LOGS}


def main() -> int:
    import torch

    torch.set_num_threads(1)
    recorded = json.loads(GOLDEN.read_text()) if GOLDEN.is_file() else {}
    mine = {}
    with tempfile.TemporaryDirectory() as folder:
        for kind, method in cases():
            mine[f"{kind}/{method}"] = digests(kind, method, Path(folder))
            print(f"{kind}/{method}: {mine[f'{kind}/{method}']['train.csv'][:12]}")
    recorded[machine_key()] = mine
    GOLDEN.parent.mkdir(exist_ok=True)
    GOLDEN.write_text(json.dumps(recorded, indent=1, sort_keys=True) + "\n")
    print(f"wrote {GOLDEN} ({machine_key()}: {len(mine)} cases)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
