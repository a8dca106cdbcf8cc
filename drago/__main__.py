"""``python -m drago ARGS``: the command line, and the one entry of a study's jobs."""

from __future__ import annotations

import os
import sys

from drago.cli import main
from drago.study.local import PARENT_ENV, become_child

if __name__ == "__main__":
    if os.environ.get(PARENT_ENV) and not become_child():
        sys.exit(1)
    sys.exit(main(sys.argv[1:]))
