"""The presets this package ships: each entry point of the group ``drago.presets`` names a YAML file."""

from importlib.resources import files

PENDULUMS_QUICK = files(__package__) / "pendulums-quick.yaml"
