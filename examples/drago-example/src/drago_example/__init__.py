"""An example drago plug-in: one continual method and one domain (see the package's README)."""
