"""``python -m sg_torchrl.sweep``: the ``sg-sweep`` command."""

import sys

from sg_torchrl.sweep.cli import main

sys.exit(main())
